"""A CoT source: friendly positions from ATAK/WinTAK/iTAK (``a-f-*``) become BlueForce events.

Listens on UDP (``udp://`` unicast or a multicast group such as ATAK's SA mesh
``udp+multicast://239.2.3.1:6969``; one event per datagram, XML or TAK protocol v1 mesh
protobuf, which ATAK switches to when all the peers it knows speak it) or on TCP (a listening
``tcp://`` socket; XML events back to back, split after each ``</event>``). Every event goes
through our validator (``sinks.cot.validate``: defusedxml, no DTDs, entities or network).

A friendly position within 0.01° of 0,0 is an ATAK device without a GPS fix (real ATAK-CIV
captures sit at -0.0043,-0.0077): it is rejected as ``no_fix``, never published. An event whose
``stale`` has passed (a replayed capture, a relay's backlog) is not a current position:
``stale``; one whose ``time`` is more than ``FUTURE_TOLERANCE`` ahead of our clock would lock
its uid out (every genuine report would look older): ``future``. Per uid only the newest
``time`` is published: an older event is ``older``, the same one again ``duplicate`` (the
newest times of at most ``max_uids`` uids are kept). Nothing here raises on bad input; every
event is counted by outcome in ``counts`` (``accepted``, ``no_fix``, ``not_friendly``,
``stale``, ``future``, ``older``, ``duplicate``, ``control`` for a mesh ``TakControl`` without
an event, ``invalid``, ``oversize``, ``fragment`` for stream bytes that
were not an event), invalid ones also by ``problems``, and logged rate-limited without the
payload. The TCP side and its bounds are in ``sinks.cot.stream``.

Anyone who can reach the port is a sender, so every BlueForce from here is ``unauthenticated``
(``gateway.domain.peertext.Provenance``) and its callsign is made safe (``safe_text``) here;
whatever shows it later marks it "unauthenticated CoT callsign".
"""

from __future__ import annotations

import socket
import struct
from collections import Counter
from collections.abc import Callable
from datetime import datetime, timedelta
from typing import ClassVar, Literal
from urllib.parse import urlsplit

import anyio
import anyio.abc
import structlog
from pydantic import Field, field_validator

from gateway.c2.newest import NewestTimes
from gateway.c2.source import SourceConfig
from gateway.clock import utc_now
from gateway.domain.peertext import safe_text
from gateway.events import BlueForce, Event, Position, Provenance, event_id, plausible_alt
from gateway.ops.logsetup import RateLimit
from gateway.transports.udp import is_multicast
from sinks.cot.stream import CotStreamServer
from sinks.cot.validate import CotError, ParsedCot, is_unknown, parse_cot

__all__ = ["FUTURE_TOLERANCE", "NO_FIX_DEG", "CotSource", "CotSourceConfig"]

log = structlog.get_logger(__name__)

#: Friendly positions closer than this to 0,0 (in both latitude and longitude) have no fix.
NO_FIX_DEG = 0.01
#: How far ahead of our clock an event's ``time`` may be (device clocks drift; GPS time is close).
FUTURE_TOLERANCE = timedelta(seconds=60)
_SCHEMES = ("udp", "udp+multicast", "tcp")


class CotSourceConfig(SourceConfig):
    """A CoT input: ``udp://HOST:PORT``, ``udp+multicast://GROUP:PORT`` or ``tcp://HOST:PORT``.

    For UDP, HOST is the address to bind (or a multicast group to join on ``interface``); for
    TCP, the address to listen on. Port 0 picks a free port (see ``CotSource.local_port``).
    """

    type: Literal["cot"] = Field(default="cot", description="The source type (only cot today).")
    name: str = Field(
        default="cot",
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$",
        description="Named in metrics and /status.",
    )
    uri: str = Field(
        description="udp://HOST:PORT, udp+multicast://GROUP:PORT or tcp://HOST:PORT to listen on."
    )
    interface: str = Field(
        default="0.0.0.0",  # noqa: S104 - the multicast join's interface, not a bind address
        description="IPv4 address of the interface that joins the multicast group.",
    )
    max_event_bytes: int = Field(
        default=16384, ge=512, le=65536, description="Largest CoT event read; more is refused."
    )
    max_clients: int = Field(default=32, ge=1, description="TCP connections served at once.")
    idle_timeout_s: float = Field(
        default=300.0, gt=0, description="Close a TCP connection silent for this long."
    )
    max_uids: int = Field(
        default=10_000, ge=1, description="Units whose newest time is remembered (order check)."
    )

    @field_validator("uri")
    @classmethod
    def _check_uri(cls, value: str) -> str:
        parts = urlsplit(value)
        try:
            port = parts.port
        except ValueError:
            port = None
        if parts.scheme not in _SCHEMES or not parts.hostname or port is None:
            raise ValueError(f"expected udp://, udp+multicast:// or tcp://HOST:PORT, got {value!r}")
        if parts.scheme == "udp+multicast" and not is_multicast(parts.hostname):
            raise ValueError(f"{value!r}: {parts.hostname} is not a multicast group")
        return value


class CotSource:
    """Receives CoT and publishes a ``BlueForce`` for each current friendly position."""

    config_model: ClassVar[type[CotSourceConfig]] = CotSourceConfig

    def __init__(
        self,
        name: str,
        config: CotSourceConfig,
        publish: Callable[[Event], bool],
        *,
        clock: Callable[[], datetime] = utc_now,
    ) -> None:
        self.name = name
        self.config = config
        self._publish = publish
        self._clock = clock
        parts = urlsplit(config.uri)
        self.host, self.port = str(parts.hostname), int(parts.port or 0)
        self.is_udp = parts.scheme.startswith("udp")
        #: Events by outcome (see the module docstring).
        self.counts: Counter[str] = Counter()
        #: Invalid events by the validator's problem code (xml, time, position, ...).
        self.problems: Counter[str] = Counter()
        self._newest = NewestTimes(config.max_uids)
        self._log_limit = RateLimit(interval_s=10.0)
        self.log = log.bind(source=name)
        self._stream = CotStreamServer(
            self.host,
            self.port,
            self.handle,
            self._reject,
            max_clients=config.max_clients,
            max_event_bytes=config.max_event_bytes,
            idle_timeout_s=config.idle_timeout_s,
            name=name,
        )
        self._udp_port = 0

    @property
    def local_port(self) -> int:
        """The bound port (after ``run`` has started)."""
        return self._udp_port if self.is_udp else self._stream.local_port

    @property
    def connections(self) -> Counter[str]:
        """TCP connection outcomes: accept_failed, refused, evicted, idle_closed (non-zero)."""
        stats = self._stream.stats
        outcomes = Counter(
            {
                "accept_failed": stats.accept_errors,
                "refused": stats.refused,
                "evicted": stats.evicted,
                **self._stream.counts,
            }
        )
        return +outcomes  # only the outcomes that happened

    @property
    def refused_clients(self) -> int:
        """TCP connections closed because ``max_clients`` were held (refused or evicted)."""
        stats = self._stream.stats
        return stats.refused + stats.evicted

    def status(self) -> dict[str, object]:
        """What /status shows for this source."""
        return {
            "source": self.name,
            "type": "cot",
            "uri": self.config.uri,
            "counts": dict(self.counts),
            "connections": dict(self.connections),
        }

    @property
    def parsed(self) -> int:
        """Events that passed validation, published or not."""
        return sum(
            self.counts[k]
            for k in (
                "accepted",
                "no_fix",
                "not_friendly",
                "stale",
                "future",
                "older",
                "duplicate",
            )
        )

    def _reject(self, outcome: str, **fields: object) -> None:
        self.counts[outcome] += 1
        if self._log_limit.allow(outcome):
            self.log.warning("cot_event_rejected", outcome=outcome, **fields)

    def handle(self, data: bytes) -> None:
        """Take one event's bytes (XML or TAK protobuf); publish, or count why not. Never raises."""
        if len(data) > self.config.max_event_bytes:
            self._reject("oversize", size=len(data))
            return
        try:
            cot = parse_cot(data)
        except CotError as exc:
            if exc.problem == "not_event":
                self.counts["control"] += 1  # a mesh peer's TakControl: not an error
                return
            self.problems[exc.problem] += 1
            self._reject("invalid", problem=exc.problem)
            return
        if not cot.type.startswith("a-f-"):
            self.counts["not_friendly"] += 1
            return
        now = self._clock()
        if cot.stale <= now:
            self._reject("stale", uid=cot.uid, stale=cot.stale.isoformat())
            return
        if cot.time > now + FUTURE_TOLERANCE:
            # Accepted, a time in the future would make every genuine report "older" until it.
            self._reject("future", uid=cot.uid, time=cot.time.isoformat())
            return
        if abs(cot.lat) < NO_FIX_DEG and abs(cot.lon) < NO_FIX_DEG:
            self._reject("no_fix", uid=cot.uid)
            return
        refusal = self._newest.refusal(cot.uid, cot.time)
        if refusal is not None:
            self._reject(refusal, uid=cot.uid)
            return
        self._newest.remember(cot.uid, cot.time)
        self.counts["accepted"] += 1
        self._publish(_blue_force(cot, self.name))

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind, report started, and receive until cancelled. Bind errors raise ``OSError``."""
        if self.is_udp:
            await self._run_udp(task_status)
        else:
            await self._stream.run(task_status=task_status)

    def _udp_socket(self) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            multicast = is_multicast(self.host)
            # Bound to the group itself, the socket gets that group's datagrams and no others.
            sock.bind((self.host, self.port))
            if multicast:
                membership = struct.pack(
                    "4s4s", socket.inet_aton(self.host), socket.inet_aton(self.config.interface)
                )
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
            sock.setblocking(False)
        except BaseException:
            sock.close()
            raise
        return sock

    async def _run_udp(self, task_status: anyio.abc.TaskStatus[None]) -> None:
        sock = self._udp_socket()
        with sock:
            self._udp_port = int(sock.getsockname()[1])
            task_status.started()
            while True:
                await anyio.wait_readable(sock)
                try:
                    data = sock.recv(65_536)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError as exc:  # e.g. ICMP errors surfacing on the socket
                    if self._log_limit.allow("receive"):
                        self.log.warning("cot_receive_failed", error=str(exc))
                    continue
                self.handle(data)


def _blue_force(cot: ParsedCot, source_name: str) -> BlueForce:
    """Anyone who reaches a CoT port may send: unauthenticated, its callsign made safe."""
    return BlueForce(
        event_id=event_id("cot", cot.uid, int(cot.time.timestamp() * 1000)),
        uid=cot.uid,
        time=cot.time,
        callsign=safe_text(cot.callsign),
        position=Position(
            lat_deg=cot.lat,
            lon_deg=cot.lon,
            alt_hae_m=None if is_unknown(cot.hae) else plausible_alt(cot.hae),
        ),
        source="cot",
        source_name=source_name,
        provenance=Provenance.UNAUTHENTICATED,
    )
