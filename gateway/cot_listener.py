"""A CoT source: friendly positions from ATAK/WinTAK (a-f-*) become BlueForce events.

Listens on UDP (joining a multicast group such as the ATAK SA mesh 239.2.3.1:6969, or
unicast) or TCP (a stream of XML events, split after each ``</event>``). Every event is
validated (``gateway.cot_validate``); friendly positions within 0.01° of 0,0 are an ATAK
without a GPS fix and are rejected, not plotted. Nothing here raises on bad input: it is counted by
outcome and logged, rate-limited.
"""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import Callable
from ipaddress import ip_address
from typing import Literal
from urllib.parse import urlsplit

import anyio
import anyio.abc
import structlog
from pydantic import BaseModel, ConfigDict, Field, field_validator

from gateway.cot_validate import CotError, is_unknown, parse_cot
from gateway.events import BlueForce, Event, Position
from gateway.logsetup import RateLimit

__all__ = ["CotListener", "CotSourceConfig"]

log = structlog.get_logger(__name__)
_END = b"</event>"
# ATAK without a GPS fix reports points a few hundred metres from 0,0 (seen in real ATAK-CIV
# captures: -0.004288,-0.007681 with unknown ce); nobody we serve operates at Null Island.
_NULL_ISLAND_DEG = 0.01


class CotSourceConfig(BaseModel):
    """A CoT input: ``udp://GROUP_OR_HOST:PORT`` or ``tcp://HOST:PORT`` (listening)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    type: Literal["cot"] = "cot"
    name: str = Field(default="cot", pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    uri: str
    interface: str = Field(default="0.0.0.0", description="Interface address for multicast.")  # noqa: S104
    max_event_bytes: int = Field(default=16384, ge=512, le=65536)

    @field_validator("uri")
    @classmethod
    def _check_uri(cls, value: str) -> str:
        parts = urlsplit(value)
        if parts.scheme not in ("udp", "tcp") or not parts.hostname or parts.port is None:
            raise ValueError(f"expected udp://HOST:PORT or tcp://HOST:PORT, found {value!r}")
        return value


class CotListener:
    """Receives CoT and publishes BlueForce for friendly positions."""

    def __init__(self, config: CotSourceConfig, publish: Callable[[Event], None]) -> None:
        self.config = config
        self._publish = publish
        parts = urlsplit(config.uri)
        self.host, self.port = str(parts.hostname), int(parts.port or 0)
        self.counts: dict[str, int] = {}
        self.local_port = 0
        self._log_limit = RateLimit(interval_s=10.0)

    def _count(self, outcome: str) -> None:
        self.counts[outcome] = self.counts.get(outcome, 0) + 1

    def handle(self, data: bytes) -> None:
        """Take one CoT event's bytes; never raises."""
        if len(data) > self.config.max_event_bytes:
            self._count("oversize")
            return
        try:
            cot = parse_cot(data)
        except CotError as exc:
            self._count("invalid")
            if self._log_limit.allow("invalid"):
                log.warning("cot_rejected", source=self.config.name, reason=str(exc))
            return
        if not cot.type.startswith("a-f-"):
            self._count("not_friendly")
            return
        if abs(cot.lat) < _NULL_ISLAND_DEG and abs(cot.lon) < _NULL_ISLAND_DEG:
            self._count("no_fix")
            return
        self._count("accepted")
        self._publish(
            BlueForce(
                event_id=f"cot-{cot.uid}-{int(cot.time.timestamp() * 1000)}",
                uid=cot.uid,
                time=cot.time,
                callsign=cot.callsign,
                position=Position(
                    lat_deg=cot.lat,
                    lon_deg=cot.lon,
                    alt_hae_m=None if is_unknown(cot.hae) else cot.hae,
                ),
                source=f"cot:{self.config.name}",
            )
        )

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind, report started, and receive until cancelled."""
        if self.config.uri.startswith("udp://"):
            await self._run_udp(task_status)
        else:
            await self._run_tcp(task_status)

    async def _run_udp(self, task_status: anyio.abc.TaskStatus[None]) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        multicast = ip_address(self.host).is_multicast
        sock.bind(("0.0.0.0" if multicast else self.host, self.port))  # noqa: S104 - group join
        if multicast:
            membership = struct.pack(
                "4s4s", socket.inet_aton(self.host), socket.inet_aton(self.config.interface)
            )
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
        sock.setblocking(False)
        self.local_port = sock.getsockname()[1]
        loop = asyncio.get_running_loop()
        task_status.started()
        try:
            while True:
                data = await loop.sock_recv(sock, 65536)
                self.handle(data)
        finally:
            sock.close()

    async def _run_tcp(self, task_status: anyio.abc.TaskStatus[None]) -> None:
        listener = await anyio.create_tcp_listener(local_host=self.host, local_port=self.port)
        self.local_port = int(listener.extra(anyio.abc.SocketAttribute.local_port))
        task_status.started()
        async with listener:
            await listener.serve(self._serve)

    async def _serve(self, stream: anyio.abc.SocketStream) -> None:
        buffer = b""
        limit = self.config.max_event_bytes
        async with stream:
            try:
                while True:
                    buffer += await stream.receive(65536)
                    while (end := buffer.find(_END)) >= 0:
                        self.handle(buffer[: end + len(_END)].strip())
                        buffer = buffer[end + len(_END) :]
                    if len(buffer) > limit:
                        self._count("oversize")
                        buffer = b""
            except (anyio.EndOfStream, anyio.BrokenResourceError, OSError):
                return
