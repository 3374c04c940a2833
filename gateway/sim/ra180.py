"""A simulated Ra 180 radio gateway for the demo: Compact Data Messages over UDP.

``SimulatedRadioGateway`` owns a UDP socket on 127.0.0.1 (``port``) and reads each datagram as
one CDM by its own reading of the grammar in docs/ra180.md (``read_cdm``: at most 127
characters of A-Z, 0-9, space, ``-`` and ``/``; the mandatory fields in order, then the
optional ones), independently of the gateway's codec. The first message of each target number
goes to ``on_cdm`` as a ``Heard``: the text, its reading and, when ``voice_directory`` is
given, the Swedish announcement the gateway rendered for it (``NR<number>`` in the WAV's name),
read with ``wave``: waited for up to ``VOICE_WAIT_S``. Datagrams that are not a CDM are counted
in ``unreadable``.
"""

from __future__ import annotations

import re
import socket
import wave
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import anyio
import anyio.abc

__all__ = ["VOICE_WAIT_S", "Cdm", "Heard", "SimulatedRadioGateway", "Wav", "read_cdm"]

#: How long a message's announcement is waited for before it is told without one.
VOICE_WAIT_S = 15.0
_MAX_NUMBERS = 10_000
_MAX_CHARS = 127
_CHARSET = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 -/")
_LINE = re.compile(
    r"(?P<type>MAL|UPPD) (?P<hostility>FIENDE|MISST|OKAND) (?P<cls>[A-Z0-9/-]{1,16})"
    r" POS (?P<mgrs>\d{1,2}[C-X][A-Z]{2} (?:\d{4} \d{4}|\d{5} \d{5}))"
    r" KONF (?P<conf>\d{3}) TID (?P<dtg>\d{6}Z[A-Z]{3}\d{2}) NR (?P<nr>\d{4})"
    r"(?: KURS (?P<course>\d{3}))?(?: FART (?P<speed>\d{3}))?(?: FRAN (?P<orig>[A-Z0-9/-]+))?"
)


@dataclass(frozen=True, slots=True)
class Cdm:
    """What the net read from one message."""

    type: str
    hostility: str
    class_abbreviation: str
    mgrs: str
    confidence_pct: int
    dtg: str
    number: int
    course_deg: int | None
    speed_kmh: int | None


def read_cdm(text: str) -> Cdm | None:
    """The ``Cdm`` of ``text``, or None when it is not one."""
    if len(text) > _MAX_CHARS or not set(text) <= _CHARSET:
        return None
    match = _LINE.fullmatch(text)
    if match is None or int(match["conf"]) > 100:
        return None
    return Cdm(
        type=match["type"],
        hostility=match["hostility"],
        class_abbreviation=match["cls"],
        mgrs=match["mgrs"],
        confidence_pct=int(match["conf"]),
        dtg=match["dtg"],
        number=int(match["nr"]),
        course_deg=None if match["course"] is None else int(match["course"]),
        speed_kmh=None if match["speed"] is None else int(match["speed"]),
    )


@dataclass(frozen=True, slots=True)
class Wav:
    """A rendered announcement: its file and what ``wave`` read of it."""

    path: Path
    seconds: float
    rate_hz: int


@dataclass(frozen=True, slots=True)
class Heard:
    """One message as the net heard it, and its announcement (None: none rendered)."""

    text: str
    cdm: Cdm
    wav: Wav | None


def _read_wav(path: Path) -> Wav | None:
    try:
        with wave.open(str(path), "rb") as audio:
            rate = audio.getframerate()
            return Wav(path, audio.getnframes() / rate if rate else 0.0, rate)
    except (OSError, EOFError, wave.Error):
        return None


class SimulatedRadioGateway:
    """See the module docstring; its loopback port is bound (``port``) when it is made."""

    def __init__(self, on_cdm: Callable[[Heard], None], voice_directory: Path | None) -> None:
        self._on_cdm = on_cdm
        self.voice_directory = voice_directory
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._socket.bind(("127.0.0.1", 0))
        self.port = int(self._socket.getsockname()[1])
        self.numbers: set[int] = set()
        self.messages = 0
        self.unreadable = 0

    async def serve(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Read datagrams until cancelled."""
        udp = await anyio.abc.UDPSocket.from_socket(self._socket)
        task_status.started()
        async with udp, anyio.create_task_group() as tg:
            async for data, _ in udp:
                text = data.decode("ascii", errors="replace")
                cdm = read_cdm(text)
                if cdm is None:
                    self.unreadable += 1
                    continue
                self.messages += 1
                if cdm.number in self.numbers or len(self.numbers) >= _MAX_NUMBERS:
                    continue
                self.numbers.add(cdm.number)
                tg.start_soon(self._tell, text, cdm)

    async def _tell(self, text: str, cdm: Cdm) -> None:
        wav = None
        if self.voice_directory is not None:
            with anyio.move_on_after(VOICE_WAIT_S):
                while wav is None:
                    await anyio.sleep(0.1)
                    wav = await anyio.to_thread.run_sync(self._find_wav, cdm.number)
        self._on_cdm(Heard(text, cdm, wav))

    def _find_wav(self, number: int) -> Wav | None:
        assert self.voice_directory is not None  # noqa: S101 - only called with one
        for path in sorted(self.voice_directory.glob(f"*-NR{number:04d}-*.wav")):
            found = _read_wav(path)
            if found is not None:
                return found
        return None
