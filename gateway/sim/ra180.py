"""A simulated Ra 180 radio gateway for the demo: Compact Data Messages over UDP.

``SimulatedRadioGateway`` owns a UDP socket on 127.0.0.1 (``port``) and reads each datagram
as one CDM with ``sinks.ra180.cdm.parse_cdm``, the grammar anything listening on the net
uses. The first message of each target number goes to ``on_cdm`` as a ``Heard``: the text,
its reading and, when ``voice_directory`` is given, the Swedish announcement the gateway
rendered for it (``NR<number>`` in the WAV's name), read with ``wave``: waited for up to
``VOICE_WAIT_S``. Datagrams that are not a CDM are counted in ``unreadable``.
"""

from __future__ import annotations

import socket
import wave
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import anyio
import anyio.abc

from sinks.ra180.cdm import Cdm, CdmError, parse_cdm

__all__ = ["VOICE_WAIT_S", "Heard", "SimulatedRadioGateway", "Wav"]

#: How long a message's announcement is waited for before it is told without one.
VOICE_WAIT_S = 15.0
_MAX_NUMBERS = 10_000


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
                try:
                    text = data.decode("ascii")
                    cdm = parse_cdm(text)
                except (UnicodeDecodeError, CdmError):
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
