"""A ground station for detection acknowledgements in tests, built on pymavlink alone.

``AckPeer`` decodes and encodes with the module ``mavgen`` generates from
gateway/fleet/fischer_dialect.xml (``generate_dialect``), never with ``gateway.fleet.dialect``,
so the simulator is checked against the XML. It reads a real UDP socket on 127.0.0.1; with a
master key it opens tunnel frames and seals its answers as the gateway does, and with a
signing key it verifies what arrives and signs what it sends. It records every
FISCHER_DETECTION that arrives and answers as the test's ``answer`` says: an acknowledgement,
a decoy the airframe must ignore (another sysid; unsealed on a tunnel; unsigned on a signed
link), or nothing. ``cut`` drops whole datagrams, as a jammed link would.

In an async test::

    async with AckPeer.bound(dialect) as peer:  # peer.port
        tg.start_soon(peer.serve)
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import shutil
import time
from collections import Counter
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import ModuleType
from typing import Any, Literal

import anyio
import anyio.abc
import pymavlink
from pymavlink.generator import mavgen
from pymavlink.generator.mavparse import PROTOCOL_2_0

from gateway.errors import FrameError
from gateway.fleet.security.signing import mavlink_timestamp_now
from gateway.fleet.security.tunnel import DayKeys, Sealer, TunnelOpener

ROOT = Path(__file__).resolve().parents[1]

Answer = Literal["ack", "duplicate", "decoy", "none"]


def generate_dialect(out: Path) -> ModuleType:
    """The dialect module mavgen makes from gateway/fleet/fischer_dialect.xml, imported."""
    source = Path(pymavlink.__file__).parent / "dialects" / "v20"
    for name in ("common.xml", "standard.xml", "minimal.xml"):
        shutil.copy(source / name, out / name)
    shutil.copy(ROOT / "gateway" / "fleet" / "fischer_dialect.xml", out / "fischer.xml")
    with contextlib.redirect_stdout(io.StringIO()):
        opts = mavgen.Opts(
            output=str(out / "fischer.py"),
            wire_protocol=PROTOCOL_2_0,
            language="Python3",
            validate=False,
        )
        if not mavgen.mavgen(opts, [str(out / "fischer.xml")]):
            raise RuntimeError("mavgen failed on gateway/fleet/fischer_dialect.xml")
    spec = importlib.util.spec_from_file_location(
        f"fischer_generated_{id(out)}", out / "fischer.py"
    )
    if spec is None or spec.loader is None:
        raise RuntimeError("cannot import the generated dialect")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@dataclass(frozen=True)
class Arrival:
    """One FISCHER_DETECTION as it arrived (a re-send arrives again, identically)."""

    sysid: int
    component: int
    detection_id: int
    time_usec: int
    body: tuple[Any, ...]  # every other field, to compare re-sends with the original
    is_signed: bool

    @property
    def identity(self) -> tuple[int, int, int]:
        return (self.sysid, self.detection_id, self.time_usec)


def ack_all(_arrival: Arrival, _copy: int) -> Answer:
    return "ack"


@dataclass
class AckPeer:
    """The ground end of the detection-acknowledgement protocol; see the module docstring."""

    dialect: ModuleType
    sock: anyio.abc.UDPSocket
    answer: Callable[[Arrival, int], Answer] = ack_all
    master: bytes | None = None
    airframe_ids: dict[int, str] = field(default_factory=dict)  # sysid -> tunnel id
    signing_key: bytes | None = None
    cut: Callable[[AckPeer], bool] = lambda _peer: False
    arrivals: list[Arrival] = field(default_factory=list)
    lost: list[tuple[int, int, int]] = field(default_factory=list)  # identities cut away
    datagrams: int = 0
    rejected: int = 0  # tunnel frames that did not open
    acks_sent: int = 0
    address: tuple[str, int] | None = None  # where the last datagram came from

    def __post_init__(self) -> None:
        self._parser = self.dialect.MAVLink(None)
        self._parser.robust_parsing = True
        self._encoder = self.dialect.MAVLink(None, srcSystem=255, srcComponent=190)
        self._plain = self.dialect.MAVLink(None, srcSystem=255, srcComponent=190)
        if self.signing_key is not None:
            stamp = mavlink_timestamp_now(time.time())
            for end in (self._parser, self._encoder):
                end.signing.secret_key = self.signing_key
                end.signing.timestamp = stamp
            self._encoder.signing.sign_outgoing = True
        self._opener: TunnelOpener | None = None
        self._sealers: dict[int, Sealer] = {}
        if self.master is not None:
            keys = DayKeys(master=self.master)
            self._opener = TunnelOpener(keys, frozenset(self.airframe_ids.values()), _utc_now)
            self._sealers = {
                sysid: Sealer(name, keys, _utc_now) for sysid, name in self.airframe_ids.items()
            }
        self._copies: Counter[tuple[int, int, int]] = Counter()

    @classmethod
    @contextlib.asynccontextmanager
    async def bound(
        cls, dialect: ModuleType, port: int = 0, **kwargs: Any
    ) -> AsyncIterator[AckPeer]:
        """A peer on a new UDP socket at 127.0.0.1:``port`` (0: any free port)."""
        async with await anyio.create_udp_socket(local_host="127.0.0.1", local_port=port) as sock:
            yield cls(dialect, sock, **kwargs)

    @property
    def port(self) -> int:
        return int(self.sock.extra(anyio.abc.SocketAttribute.local_port))

    def identities(self) -> set[tuple[int, int, int]]:
        """(sysid, detection_id, time_usec) of every detection that arrived at least once."""
        return {a.identity for a in self.arrivals}

    def copies(self, identity: tuple[int, int, int]) -> list[Arrival]:
        return [a for a in self.arrivals if a.identity == identity]

    async def serve(self) -> None:
        """Receive, record and answer until cancelled."""
        async for data, (host, port) in self.sock:
            self.datagrams += 1
            self.address = (host, port)
            if self._opener is not None:
                try:
                    data = self._opener.open_frame(data, stream=(host, port)).payload
                except FrameError:
                    self.rejected += 1
                    continue
            arrivals = [self._arrival(m) for m in self._parse(data)]
            arrivals = [a for a in arrivals if a is not None]
            if self.cut(self):
                self.lost += [a.identity for a in arrivals]
                continue
            for arrival in arrivals:
                self.arrivals.append(arrival)
                self._copies[arrival.identity] += 1
                frame = self._answer(arrival, self._copies[arrival.identity])
                if frame is not None:
                    await self.sock.sendto(frame, host, port)

    def _parse(self, data: bytes) -> list[Any]:
        try:
            return list(self._parser.parse_buffer(data) or [])
        except self.dialect.MAVError:
            return []

    def _arrival(self, msg: Any) -> Arrival | None:
        if msg.get_type() != "FISCHER_DETECTION":
            return None
        body = (
            msg.lat, msg.lon, msg.alt_msl, msg.sigma_h, msg.class_id, msg.sensor,
            msg.confidence, msg.subtype,
        )  # fmt: skip
        return Arrival(
            msg.get_srcSystem(),
            msg.get_srcComponent(),
            msg.detection_id,
            msg.time_usec,
            body,
            bool(msg.get_signed()),
        )

    def _answer(self, arrival: Arrival, copy: int) -> bytes | None:
        what = self.answer(arrival, copy)
        if what == "none":
            return None
        result = 1 if what == "duplicate" else 0
        is_decoy = what == "decoy"
        # A decoy is what the airframe must not take for an ack: addressed to another system
        # on a plain link, unsealed on a tunnel, unsigned on a signed link.
        target = arrival.sysid
        if is_decoy and self._opener is None and self.signing_key is None:
            target = arrival.sysid % 255 + 1
        encoder = self._plain if is_decoy else self._encoder
        ack = self.dialect.MAVLink_fischer_detection_ack_message(
            arrival.time_usec, arrival.detection_id, target, arrival.component, result
        )
        frame = bytes(ack.pack(encoder))
        encoder.seq = (encoder.seq + 1) % 256
        if self._opener is not None and not is_decoy:
            frame = self._sealers[arrival.sysid].seal(frame)
        self.acks_sent += 0 if is_decoy else 1
        return frame


def _utc_now() -> datetime:
    return datetime.now(UTC)
