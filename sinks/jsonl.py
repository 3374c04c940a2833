"""The JSONL archive sink: one event per line, rotated by size and age, pruned by count.

Each line is ``event.model_dump_json()`` in UTF-8, ended by ``\\n`` only. Read the file with
``split("\\n")``, not ``str.splitlines()``: JSON leaves U+2028 and U+2029 unescaped, and
``splitlines`` would break a line there. ``gateway.events.event_adapter.validate_json`` turns a
line back into the event.

When the file would pass ``max_bytes``, or is ``max_age_s`` old (counted from when the sink
opened it, on the injected clock), it is renamed ``<stem>-YYYYmmddTHHMMSSZ<suffix>`` after the
UTC time it was opened (``archive-20261122T120000Z.jsonl`` for ``archive.jsonl``), with
``-1``, ``-2`` ... added if that name is taken, and only the ``keep`` newest rotated files stay.
"""

from __future__ import annotations

import errno
import os
import re
import time
from collections.abc import Callable, Sequence
from contextlib import suppress
from datetime import UTC, datetime
from pathlib import Path

import anyio
import structlog
from pydantic import Field

from gateway.c2.sink import SinkConfig
from gateway.errors import TransientSinkError
from gateway.events import Event, EventKind

__all__ = ["JsonlSink", "JsonlSinkConfig"]

log = structlog.get_logger(__name__)

_STAMP_FORMAT = "%Y%m%dT%H%M%SZ"
_FILE_MODE = 0o640


class JsonlSinkConfig(SinkConfig):
    """Options of the JSONL archive."""

    path: Path = Field(description="The live file; a relative path is taken from the cwd.")
    max_bytes: int = Field(
        default=100 * 1024 * 1024,
        ge=1024,
        description="Rotate before a batch would take the file past this size.",
    )
    max_age_s: float = Field(
        default=86_400.0, gt=0, description="Rotate once the file has been open this long."
    )
    keep: int = Field(default=30, ge=0, description="Rotated files kept; older are deleted.")
    fsync: bool = Field(default=False, description="fsync after every batch (slower, safer).")
    kinds: frozenset[EventKind] = Field(
        default=frozenset(EventKind), min_length=1, description="Event kinds this sink takes."
    )


class JsonlSink:
    """Appends events to ``config.path``, one JSON line each.

    All file work of a batch (rotation, pruning, the write, the fsync) runs in one call to a
    worker thread. ``clock`` returns wall-clock seconds since the epoch; it ages the file and
    names rotated files, and tests inject it.
    """

    config_model = JsonlSinkConfig

    def __init__(
        self, name: str, config: JsonlSinkConfig, *, clock: Callable[[], float] = time.time
    ) -> None:
        self.name = name
        self.config = config
        self.log = log.bind(sink=name)
        self._clock = clock
        self._path = config.path
        self._fd: int | None = None
        self._size = 0
        self._opened_at = 0.0

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Every kind unless the config narrows it."""
        return self.config.kinds

    async def open(self) -> None:
        """Create the directory if needed, open the live file for appending, prune old files.

        A relative ``path`` is resolved against the current directory now. Raises
        ``TransientSinkError`` naming the sink and the path on any ``OSError``.
        """
        self._path = self.config.path.absolute()
        try:
            await anyio.to_thread.run_sync(self._open_and_prune)
        except OSError as exc:
            raise self._error("open", exc) from exc

    async def send(self, batch: Sequence[Event]) -> None:
        """Append ``batch``, one line per event, in a single write (rotating first if due).

        Raises ``TransientSinkError`` on any ``OSError``, a full disk included; the bytes of a
        failed batch are cut off again where possible, so a retry does not leave half a line.
        A cancelled send waits for the worker thread, so the file is never left mid-write.
        """
        data = b"".join(event.model_dump_json().encode() + b"\n" for event in batch)
        if not data:
            return
        try:
            await anyio.to_thread.run_sync(self._write, data)
        except OSError as exc:
            raise self._error("write", exc) from exc

    async def aclose(self) -> None:
        """Close the live file; safe after a failed ``open`` and when called twice."""
        if self._fd is not None:
            fd, self._fd = self._fd, None
            await anyio.to_thread.run_sync(os.close, fd)

    def _error(self, action: str, exc: OSError) -> TransientSinkError:
        # A full disk is transient too: rotation, pruning or an operator may free space.
        full = " (disk full)" if exc.errno == errno.ENOSPC else ""
        reason = exc.strerror or type(exc).__name__
        return TransientSinkError(
            f"sink {self.name}: cannot {action} {self._path}: {reason}{full}", sink=self.name
        )

    # Everything below runs in a worker thread.

    def _open_and_prune(self) -> None:
        if self._fd is not None:  # a retried open() after pruning failed: do not leak the fd
            fd, self._fd = self._fd, None
            os.close(fd)
        self._open_file()
        self._prune()

    def _open_file(self) -> None:
        self._path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self._path, os.O_RDWR | os.O_APPEND | os.O_CREAT, _FILE_MODE)
        try:
            size = os.fstat(fd).st_size
            # A crash mid-line leaves a partial last line: end it so the next line parses.
            if size and os.pread(fd, 1, size - 1) != b"\n":
                size += os.write(fd, b"\n")
                self.log.warning("archive_partial_line_ended", path=str(self._path))
        except OSError:
            os.close(fd)
            raise
        self._fd, self._size, self._opened_at = fd, size, self._clock()
        self.log.debug("archive_opened", path=str(self._path), size_bytes=size)

    def _is_rotation_due(self, incoming: int) -> bool:
        if not self._size:
            return False  # an empty file is never rotated, whatever its age
        too_big = self._size + incoming > self.config.max_bytes
        return too_big or self._clock() - self._opened_at >= self.config.max_age_s

    def _write(self, data: bytes) -> None:
        if self._fd is None:
            self._open_file()  # reopened after a failed write, or sent to without open()
        if self._is_rotation_due(len(data)):
            self._rotate()
        fd = self._fd
        assert fd is not None  # noqa: S101 - _open_file set it or raised
        before = self._size
        try:
            view = memoryview(data)
            while view:  # one write(2) unless the kernel takes less (a full disk, a signal)
                view = view[os.write(fd, view) :]
            if self.config.fsync:
                os.fsync(fd)
        except OSError:
            # Cut the failed batch off so its retry does not follow half a line; if even that
            # fails, the reopen on the next write ends the partial line instead.
            with suppress(OSError):
                os.ftruncate(fd, before)
            self._fd = None
            os.close(fd)
            raise
        self._size = before + len(data)

    def _rotate(self) -> None:
        fd = self._fd
        assert fd is not None  # noqa: S101 - only called while the file is open
        self._fd = None
        os.close(fd)
        target = self._rotated_name()
        os.rename(self._path, target)
        if self.config.fsync:
            self._fsync_directory()
        pruned = self._prune()
        self.log.info(
            "archive_rotated", path=str(self._path), rotated_to=target.name, pruned=pruned
        )
        self._open_file()

    def _rotated_name(self) -> Path:
        stamp = datetime.fromtimestamp(self._opened_at, tz=UTC).strftime(_STAMP_FORMAT)
        stem, suffix = self._path.stem, self._path.suffix
        candidate = self._path.with_name(f"{stem}-{stamp}{suffix}")
        counter = 1
        while candidate.exists():
            candidate = self._path.with_name(f"{stem}-{stamp}-{counter}{suffix}")
            counter += 1
        return candidate

    def _prune(self) -> int:
        """Delete all but the ``keep`` newest rotated files; return how many were deleted."""
        stem, suffix = re.escape(self._path.stem), re.escape(self._path.suffix)
        pattern = re.compile(rf"{stem}-(\d{{8}}T\d{{6}}Z)(?:-(\d+))?{suffix}")
        rotated: list[tuple[str, int, Path]] = []
        for entry in self._path.parent.iterdir():
            match = pattern.fullmatch(entry.name)
            if match:
                rotated.append((match[1], int(match[2] or 0), entry))
        # By name, not mtime: the stamp and counter order files exactly, whatever the clock.
        rotated.sort()
        doomed = rotated[: max(0, len(rotated) - self.config.keep)]
        for _, _, old in doomed:
            old.unlink(missing_ok=True)
        return len(doomed)

    def _fsync_directory(self) -> None:
        dir_fd = os.open(self._path.parent, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
