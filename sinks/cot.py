"""The CoT sink: own airframes, detections and tracks to ATAK/WinTAK/iTAK and TAK servers.

Destinations: UDP multicast (the ATAK SA mesh, 239.2.3.1:6969) or unicast, XML or TAK
protocol protobuf (mesh framing); TCP (8087) and TLS with a client certificate (8089) to a
TAK server, as an XML stream or, after the server's protocol offer, protobuf stream framing.
Each event is built once and encoded per destination. TLS always verifies the server against
the configured CA and hostname; there is no switch to turn that off.

Tracks are sent on change: an unchanged track is not re-sent until half its stale time has
passed, which keeps thin links free for news. The sink keeps no queue and does no retrying:
a failure raises ``TransientSinkError`` and the SinkRunner retries the batch.
"""

from __future__ import annotations

import socket
import ssl
import tempfile
from collections.abc import Sequence
from datetime import datetime, timedelta
from ipaddress import ip_address
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

import anyio
import anyio.abc
import structlog
from pydantic import BaseModel, ConfigDict, Field, field_validator

from gateway.errors import TransientSinkError
from gateway.events import Event, EventKind, Track
from gateway.sink import SinkConfig
from sinks._cot_codec import mesh_frame, stream_frame, to_proto, to_xml
from sinks._cot_event import CotEvent, CotOptions, build
from sinks._cot_geoid import GeoidGrid

__all__ = ["CotDestination", "CotSink", "CotSinkConfig", "CotTls"]

log = structlog.get_logger(__name__)
_OFFER = b"t-x-takp-v"
_RESPONSE = b"t-x-takp-r"


class CotTls(BaseModel):
    """Client certificate (PEM pair or PKCS#12) and the pinned CA of a TAK server."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    ca_file: Path = Field(description="The CA that must have signed the server's certificate.")
    cert_file: Path | None = None
    key_file: Path | None = None
    pkcs12_file: Path | None = None
    password_file: Path | None = Field(default=None, description="For the key or PKCS#12.")
    server_hostname: str | None = Field(default=None, description="Defaults to the URI host.")


class CotDestination(BaseModel):
    """One place CoT goes: ``udp://``, ``tcp://`` or ``tls://`` HOST:PORT."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    uri: str
    protocol: Literal["xml", "protobuf", "negotiate"] = "xml"
    ttl: int = Field(default=1, ge=1, le=255, description="Multicast TTL.")
    interface: str | None = Field(default=None, description="Multicast interface address.")
    tls: CotTls | None = None

    @field_validator("uri")
    @classmethod
    def _check_uri(cls, value: str) -> str:
        parts = urlsplit(value)
        if parts.scheme not in ("udp", "tcp", "tls") or not parts.hostname or not parts.port:
            raise ValueError(f"expected udp://, tcp:// or tls://HOST:PORT, found {value!r}")
        return value


class CotSinkConfig(SinkConfig):
    """Options of the CoT sink."""

    destinations: tuple[CotDestination, ...] = Field(min_length=1)
    kinds: frozenset[EventKind] = frozenset(
        {EventKind.TELEMETRY, EventKind.DETECTION, EventKind.TRACK}
    )
    stale_s: dict[str, float] = Field(
        default_factory=lambda: {"telemetry": 15.0, "detection": 120.0, "track": 300.0}
    )
    uid_prefix: str = "fischer-"
    callsign_prefix: str = "FISCHER "
    loitering_munition: Literal["uav_attack", "missile"] = "uav_attack"
    geoid_file: Path | None = Field(
        default=None, description="EGM96 .gtx grid (Debian proj-data: egm96_15.gtx) for hae."
    )
    connect_timeout_s: float = Field(default=5.0, gt=0)
    negotiate_wait_s: float = Field(
        default=3.0, gt=0, description="How long to wait for a TAK server's protocol offer."
    )


def _tls_context(tls: CotTls) -> ssl.SSLContext:
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(tls.ca_file))
    context.check_hostname = True
    context.verify_mode = ssl.CERT_REQUIRED
    password = tls.password_file.read_bytes().strip() if tls.password_file else None
    if tls.pkcs12_file is not None:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.serialization import pkcs12

        key, cert, extra = pkcs12.load_key_and_certificates(tls.pkcs12_file.read_bytes(), password)
        if key is None or cert is None:
            raise ValueError(f"{tls.pkcs12_file} holds no key and certificate")
        with tempfile.TemporaryDirectory() as tmp:
            # ssl loads chains from files only; the directory is private and gone at once.
            pem = Path(tmp) / "client.pem"
            pem.touch(mode=0o600)
            chain = [cert, *(extra or [])]
            pem.write_bytes(
                key.private_bytes(
                    serialization.Encoding.PEM,
                    serialization.PrivateFormat.PKCS8,
                    serialization.NoEncryption(),
                )
                + b"".join(c.public_bytes(serialization.Encoding.PEM) for c in chain)
            )
            context.load_cert_chain(str(pem))
    elif tls.cert_file is not None:
        context.load_cert_chain(str(tls.cert_file), tls.key_file and str(tls.key_file), password)
    return context


class _Udp:
    def __init__(self, dest: CotDestination) -> None:
        parts = urlsplit(dest.uri)
        self.address = (str(parts.hostname), int(parts.port or 0))
        self.protobuf = dest.protocol == "protobuf"
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        if ip_address(self.address[0]).is_multicast:
            self.sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, dest.ttl)
            if dest.interface:
                self.sock.setsockopt(
                    socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(dest.interface)
                )

    async def send(self, events: list[CotEvent]) -> None:
        for event in events:
            data = mesh_frame(to_proto(event)) if self.protobuf else to_xml(event)
            await anyio.wait_writable(self.sock)
            self.sock.sendto(data, self.address)

    async def aclose(self) -> None:
        self.sock.close()


class _Stream:
    """A TAK server stream; negotiates protobuf when asked, and drains what the server sends."""

    def __init__(self, dest: CotDestination, config: CotSinkConfig) -> None:
        parts = urlsplit(dest.uri)
        self.dest = dest
        self.host, self.port = str(parts.hostname), int(parts.port or 0)
        self.config = config
        self.context = _tls_context(dest.tls) if dest.tls else None
        if parts.scheme == "tls" and self.context is None:
            raise ValueError(f"{dest.uri}: a tls:// destination needs its 'tls' section")
        self.stream: anyio.abc.ByteStream | None = None
        self.protobuf = dest.protocol == "protobuf"
        self._buffer = b""

    async def connect(self, tg: anyio.abc.TaskGroup) -> None:
        with anyio.fail_after(self.config.connect_timeout_s):
            if self.context is not None:
                hostname = (self.dest.tls and self.dest.tls.server_hostname) or self.host
                self.stream = await anyio.connect_tcp(
                    self.host, self.port, ssl_context=self.context, tls_hostname=hostname,
                    tls_standard_compatible=False,
                )  # fmt: skip
            else:
                self.stream = await anyio.connect_tcp(self.host, self.port)
        if self.dest.protocol == "negotiate":
            self.protobuf = await self._negotiate()
        tg.start_soon(self._drain, self.stream)

    async def _read_until(self, marker: bytes) -> bool:
        assert self.stream is not None  # noqa: S101 - connected
        while marker not in self._buffer:
            chunk = await self.stream.receive(65536)
            self._buffer = (self._buffer + chunk)[-262144:]
        return True

    async def _negotiate(self) -> bool:
        """Wait for the server's offer, ask for version 1, switch if it agrees."""
        assert self.stream is not None  # noqa: S101 - connected
        with anyio.move_on_after(self.config.negotiate_wait_s):
            await self._read_until(_OFFER)
        if _OFFER not in self._buffer or b'version="1"' not in self._buffer:
            log.info("tak_protocol_stays_xml", destination=self.dest.uri, reason="no offer")
            return False
        now = datetime.now().astimezone()
        stale = now + timedelta(minutes=1)
        request = CotEvent(
            uid=f"{self.config.uid_prefix}takp-request", type="t-x-takp-q", how="m-g",
            time=now, start=now, stale=stale, lat=0.0, lon=0.0,
            xml_detail='<TakControl><TakRequest version="1"/></TakControl>',
        )  # fmt: skip
        await self.stream.send(to_xml(request))
        with anyio.move_on_after(self.config.negotiate_wait_s):
            await self._read_until(_RESPONSE)
        agreed = _RESPONSE in self._buffer and b'status="true"' in self._buffer
        log.info("tak_protocol_negotiated", destination=self.dest.uri, protobuf=agreed)
        self._buffer = b""
        return agreed

    async def _drain(self, stream: anyio.abc.ByteStream) -> None:
        # A TAK server relays other clients' events to us; read and discard them so its
        # send buffer never fills. Never raises: a broken stream shows up on the next send.
        try:
            while True:
                await stream.receive(65536)
        except (anyio.EndOfStream, anyio.BrokenResourceError, anyio.ClosedResourceError, OSError):
            return

    async def send(self, events: list[CotEvent]) -> None:
        assert self.stream is not None  # noqa: S101 - connected before send
        if self.protobuf:
            data = b"".join(stream_frame(to_proto(e)) for e in events)
        else:
            data = b"".join(to_xml(e) for e in events)
        await self.stream.send(data)

    async def aclose(self) -> None:
        if self.stream is not None:
            with anyio.move_on_after(1, shield=True):
                await self.stream.aclose()
            self.stream = None


class CotSink:
    """Sends own airframes, detections and tracks as CoT to every configured destination."""

    config_model = CotSinkConfig

    def __init__(self, name: str, config: CotSinkConfig) -> None:
        self.name = name
        self.config = config
        geoid = GeoidGrid(config.geoid_file) if config.geoid_file else None
        self.options = CotOptions(
            uid_prefix=config.uid_prefix,
            callsign_prefix=config.callsign_prefix,
            stale_s=dict(config.stale_s),
            loitering_munition=config.loitering_munition,
            geoid=geoid.undulation if geoid else None,
        )
        self._transports: list[_Udp | _Stream] = []
        self._tg: anyio.abc.TaskGroup | None = None
        self._last_track: dict[str, tuple[tuple[object, ...], datetime]] = {}

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Telemetry, detections and tracks unless the config narrows it."""
        return self.config.kinds

    async def open(self) -> None:
        """Open every destination; a failure to connect is transient (retried)."""
        # The task group holding the stream drain tasks is entered here and left in aclose();
        # the SinkRunner calls both from its own task, so the scopes nest correctly.
        self._tg = anyio.create_task_group()
        await self._tg.__aenter__()
        try:
            await self._connect()
        except BaseException:
            # Leave the task group now: the caller's scopes must unwind in order.
            await self.aclose()
            raise

    async def _connect(self) -> None:
        assert self._tg is not None  # noqa: S101 - open() came first
        dest = None
        try:
            for dest in self.config.destinations:
                if dest.uri.startswith("udp://"):
                    self._transports.append(_Udp(dest))
                else:
                    stream = _Stream(dest, self.config)
                    self._transports.append(stream)
                    await stream.connect(self._tg)
        except (OSError, TimeoutError, ssl.SSLError, anyio.BrokenResourceError) as exc:
            await self._disconnect()
            where = dest.uri if dest is not None else "?"
            raise TransientSinkError(
                f"sink {self.name}: cannot reach {where}: {exc}", sink=self.name
            ) from exc

    async def _disconnect(self) -> None:
        transports, self._transports = self._transports, []
        for transport in transports:
            await transport.aclose()

    def _changed(self, event: Track, cot: CotEvent) -> bool:
        content = (
            cot.type,
            cot.lat,
            cot.lon,
            cot.ce,
            cot.course_deg,
            cot.speed_mps,
            cot.xml_detail,
        )
        last = self._last_track.get(cot.uid)
        refresh = timedelta(seconds=self.options.stale_s["track"] / 2)
        if last is not None and last[0] == content and event.time - last[1] < refresh:
            return False
        self._last_track[cot.uid] = (content, event.time)
        return True

    async def send(self, batch: Sequence[Event]) -> None:
        """Build each event once and send it to every destination."""
        events: list[CotEvent] = []
        for event in batch:
            cot = build(event, self.options)
            if cot is None:
                continue
            if isinstance(event, Track) and not self._changed(event, cot):
                continue
            events.append(cot)
        if not events:
            return
        if not self._transports:
            await self._connect()  # after a failure: reconnect, or raise to be retried
        for transport in self._transports:
            try:
                await transport.send(events)
            except (OSError, anyio.BrokenResourceError, anyio.ClosedResourceError) as exc:
                await self._disconnect()
                where = getattr(transport, "dest", None)
                raise TransientSinkError(
                    f"sink {self.name}: send to {where.uri if where else 'udp'} failed: {exc}",
                    sink=self.name,
                ) from exc

    async def aclose(self) -> None:
        """Close every destination and stop the drain tasks."""
        await self._disconnect()
        tg, self._tg = self._tg, None
        if tg is not None:
            tg.cancel_scope.cancel()
            await tg.__aexit__(None, None, None)
