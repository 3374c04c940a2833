"""The Ra 180 sink's spoken announcements: espeak-ng's Swedish voice to one WAV file each.

``Voice.submit(cdm)`` queues an announcement (a bounded queue: when full, the oldest waiting
one is dropped and counted), and ``Voice.run`` renders them one at a time in a subprocess,
``espeak-ng -v sv -w FILE`` with the text on stdin, under a deadline, so the event loop never
waits on synthesis. Each WAV is written under a temporary name and renamed into ``directory``
whole, so whatever plays the files to the radio's audio input never reads half of one; the
directory is kept to ``max_files`` and ``max_bytes`` of announcements, oldest removed first.

A missing espeak-ng is not an error of the gateway: the voice reports itself
``unavailable`` with the reason (install the Debian package ``espeak-ng``), logs it once,
counts each announcement it could not make, and the CDMs still go out.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
from collections import deque
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import anyio
import anyio.to_thread
import structlog

from gateway.ops.logsetup import RateLimit
from sinks.ra180.cdm import Cdm
from sinks.ra180.phrases import announcement

__all__ = ["ANNOUNCEMENT_NAME", "Voice", "VoiceCounts", "VoiceSettings", "prune"]

log = structlog.get_logger(__name__)

_MISSING = "not found on PATH: install the Debian package espeak-ng"
#: The names this voice gives its files; ``prune`` removes nothing else from the directory.
ANNOUNCEMENT_NAME = re.compile(r"^\d{8}T\d{12}Z-\d{6}-NR\d{4}-(?:MAL|UPPD)\.wav$")


@dataclass(frozen=True, slots=True)
class VoiceSettings:
    """Where and how announcements are rendered (``Ra180VoiceConfig`` validates them)."""

    directory: Path
    program: str = "espeak-ng"
    voice: str = "sv"
    words_per_minute: int = 140
    timeout_s: float = 20.0
    max_files: int = 200
    max_bytes: int = 50_000_000
    queue_max: int = 16


@dataclass(slots=True)
class VoiceCounts:
    """What became of the announcements asked for."""

    rendered: int = 0
    failed: int = 0
    dropped: int = 0
    unavailable: int = 0
    removed: int = 0


def prune(directory: Path, max_files: int, max_bytes: int) -> int:
    """Remove the oldest announcements until at most ``max_files`` and ``max_bytes`` remain.

    Only files named as this voice names them (``ANNOUNCEMENT_NAME``) are counted or removed:
    the directory may be shared with other audio (a player's folder), which is not ours to
    delete. Oldest by name (names start with the UTC time they were written). Returns how
    many were removed; files that vanish meanwhile are skipped. Blocking: run it in a worker
    thread.
    """
    files = []
    for path in directory.glob("*.wav"):
        if not ANNOUNCEMENT_NAME.match(path.name):
            continue
        try:
            files.append((path.name, path, path.stat().st_size))
        except OSError:
            continue
    files.sort()
    total = sum(size for _, _, size in files)
    removed = 0
    for _, path, size in files:
        if len(files) - removed <= max_files and total <= max_bytes:
            break
        try:
            path.unlink(missing_ok=True)
        except OSError:
            break  # not ours to remove (permissions): keep the rest, try at the next file
        total -= size
        removed += 1
    return removed


class Voice:
    """Renders announcements to WAV files, one at a time, off the event loop."""

    def __init__(self, settings: VoiceSettings, *, sink: str) -> None:
        self.settings = settings
        self.counts = VoiceCounts()
        self.state = "starting"
        self.reason = ""
        self.last_file: Path | None = None
        self._queue: deque[Cdm] = deque()
        self._wake = anyio.Event()
        self._serial = 0
        self._fail_log = RateLimit(interval_s=30.0)
        self.log = log.bind(sink=sink)

    def submit(self, cdm: Cdm) -> None:
        """Queue ``cdm``'s announcement; never blocks (the oldest waiting one gives way)."""
        if len(self._queue) >= self.settings.queue_max:
            self._queue.popleft()
            self.counts.dropped += 1
        self._queue.append(cdm)
        self._wake.set()

    @property
    def waiting(self) -> int:
        """Announcements queued and not yet rendered."""
        return len(self._queue)

    async def run(self) -> None:
        """Render queued announcements until cancelled.

        While unavailable (no synthesiser on ``PATH``, no directory), each announcement looks
        again first, so installing espeak-ng on a running node brings the voice back.
        """
        program = await self._find()
        while True:
            while not self._queue:
                await self._wake.wait()
                self._wake = anyio.Event()
            cdm = self._queue.popleft()
            if program is None or self.state == "unavailable":
                program = await self._find()
            if program is None:
                self.counts.unavailable += 1
                continue
            await self._render(program, cdm)

    async def _find(self) -> str | None:
        """The synthesiser's path with the directory made, or None (and ``unavailable``)."""
        program = shutil.which(self.settings.program)
        if program is None:
            self._unavailable(f"{self.settings.program} {_MISSING}")
            return None
        was_unavailable = self.state == "unavailable"
        await anyio.to_thread.run_sync(self._make_directory)
        if self.state != "ready":
            return None
        if was_unavailable:
            self.log.info("ra180_voice_ready", program=program)
        return program

    def _make_directory(self) -> None:
        try:
            self.settings.directory.mkdir(parents=True, exist_ok=True)
            # Partial files of renderings a stopped gateway never finished: ours, unplayable.
            for stale in self.settings.directory.glob(".*.wav.part"):
                if ANNOUNCEMENT_NAME.match(stale.name[1 : -len(".part")]):
                    _discard(stale)
        except OSError as exc:
            self._unavailable(f"cannot create {self.settings.directory}: {exc.strerror or exc}")
        else:
            self.state, self.reason = "ready", ""

    async def _failed(self, reason: str, partial: Path) -> None:
        self.counts.failed += 1
        self.reason = reason
        if self._fail_log.allow("render"):
            self.log.warning("ra180_voice_failed", error=reason, failed=self.counts.failed)
        await anyio.to_thread.run_sync(_discard, partial)

    def _unavailable(self, reason: str) -> None:
        if (self.state, self.reason) != ("unavailable", reason):  # logged once, not per try
            self.log.warning("ra180_voice_unavailable", reason=reason)
        self.state, self.reason = "unavailable", reason

    async def _render(self, program: str, cdm: Cdm) -> None:
        s = self.settings
        self._serial += 1
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
        name = f"{stamp}-{self._serial:06d}-NR{cdm.number:04d}-{cdm.type}.wav"
        final = s.directory / name
        partial = s.directory / f".{name}.part"
        command = [program, "-v", s.voice, "-s", str(s.words_per_minute), "-b", "1"]
        command += ["-w", str(partial), "--stdin"]
        try:
            with anyio.fail_after(s.timeout_s):
                done = await anyio.run_process(
                    command, input=announcement(cdm).encode(), check=False
                )
        except FileNotFoundError:
            self._unavailable(f"{s.program} {_MISSING}")
            self.counts.unavailable += 1
            return
        except TimeoutError:
            await self._failed(f"{s.program} did not finish within {s.timeout_s:g} s", partial)
            return
        except OSError as exc:
            await self._failed(f"{s.program}: {exc.strerror or exc}", partial)
            return
        if done.returncode != 0:
            detail = done.stderr.decode(errors="replace").strip()[:200]
            await self._failed(f"{s.program} exited {done.returncode}: {detail}", partial)
            return
        try:
            await anyio.to_thread.run_sync(os.replace, partial, final)
        except OSError as exc:
            await self._failed(f"cannot keep {final}: {exc.strerror or exc}", partial)
            return
        self.counts.rendered += 1
        self.last_file = final
        self.state, self.reason = "ready", ""
        self.counts.removed += await anyio.to_thread.run_sync(
            prune, s.directory, s.max_files, s.max_bytes
        )


def _discard(path: Path) -> None:
    """Remove ``path`` if it is there (a partial file of a failed rendering)."""
    with contextlib.suppress(OSError):
        path.unlink(missing_ok=True)
