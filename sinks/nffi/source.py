"""The NFFI source: friendly-force reports received as NFFI 1.3 (IP1) become BlueForce events.

The relay path for friendly reports, including those of JAS 39 aircraft: a C2 system connects
over TCP (``tcp://``) or TLS with a client certificate (``tls://``) and sends NFFI documents
back to back (framing: ``sinks.nffi.stream``); each track becomes a ``BlueForce``
(``source`` ``nffi``, ``uid`` its trackSource, speed converted from km/h to m/s, the unit
symbol kept as ``sidc``) that every routed sink gets. docs/nffi.md has the mapping and the
trust model.

Everything received is hostile until checked. A peer whose address is not in ``allow`` is
closed before a byte is read; on ``tls://`` a peer without a certificate from ``client_ca_file``
fails the handshake. Documents are parsed with defusedxml, at most ``max_message_bytes`` each
(more without a document end, and the connection is closed); the listener
(``gateway.transports.listener``) bounds connections (``max_clients``, eviction of the
stalest that never sent a document, ``idle_timeout_s``). A track is published only if it is
current: not older than ``max_age_s`` (``stale``), not ahead of our clock by more than
``FUTURE_TOLERANCE`` (``future``), not at 0,0 (``no_fix``), not a hostile symbol
(``not_friendly``: NFFI carries friendly forces only), and newer than the last one of its
trackSource (``older``, ``duplicate``; the newest times of ``max_units`` units are kept).
Nothing here raises on bad input: every outcome is counted (``counts``), invalid documents
and skipped tracks also by ``problems``, and logged at most once per ``LOG_INTERVAL_S`` per
outcome, without the payload.

Each BlueForce says how far its sender was checked (``provenance``): ``authenticated`` on
``tls://`` (the peer's certificate chains to ``client_ca_file``), ``address_only`` on
``tcp://`` (an allow-listed address, not an authenticated sender). Its callsign (unit short
name or transponder id) is made safe here (``gateway.domain.peertext.safe_text``).
"""

from __future__ import annotations

import ipaddress
import ssl
from collections import Counter
from collections.abc import Awaitable, Callable
from datetime import datetime, timedelta
from pathlib import Path
from typing import Annotated, ClassVar, Literal
from urllib.parse import urlsplit

import anyio
import anyio.abc
import structlog
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from gateway.c2.newest import NewestTimes
from gateway.c2.source import SourceConfig
from gateway.clock import utc_now
from gateway.domain.peertext import safe_text
from gateway.events import BlueForce, Event, Position, Provenance, event_id
from gateway.ops.logsetup import RateLimit
from gateway.transports.listener import Connection, TcpListener
from gateway.transports.tls import TlsFiles, unreadable_file
from sinks.nffi.codec import MAX_MESSAGE_BYTES, NffiError, NffiTrack, parse_message
from sinks.nffi.stream import MessageSplitter

__all__ = ["FUTURE_TOLERANCE", "LOG_INTERVAL_S", "NffiSource", "NffiSourceConfig", "NffiSourceTls"]

log = structlog.get_logger(__name__)

#: How far ahead of our clock a track's ``dateTime`` may be.
FUTURE_TOLERANCE = timedelta(seconds=60)
#: At most one log record per outcome per this many seconds (every one is counted).
LOG_INTERVAL_S = 10.0
_NO_FIX_DEG = 0.01
#: Standard identities of a letter SIDC that are not friendly (hostile, suspect, joker, faker,
#: neutral, unknown, pending): NFFI must not make them blue.
_NOT_FRIENDLY = frozenset("HSJKNUPGWL")
_FROZEN = ConfigDict(frozen=True, extra="forbid")
_Network = ipaddress.IPv4Network | ipaddress.IPv6Network


def _network(value: object) -> object:
    """An allow-list entry as a network, with an error that says how to write it."""
    if isinstance(value, ipaddress.IPv4Network | ipaddress.IPv6Network):
        return value
    if not isinstance(value, str):
        raise ValueError("expected an IP address or network as text, e.g. 10.20.1.0/24")
    try:
        return ipaddress.ip_network(value.strip())
    except ValueError:
        pass
    try:
        loose = ipaddress.ip_network(value.strip(), strict=False)
    except ValueError:
        raise ValueError("not an IP address or network (e.g. 10.20.1.5 or 10.20.1.0/24)") from None
    host = value.strip().split("/", 1)[0]
    raise ValueError(
        f"host bits set: write {loose} for the network, or "
        f"{host}/{loose.max_prefixlen} for the one address"
    )


_AllowedNetwork = Annotated[_Network, BeforeValidator(_network)]


class NffiSourceTls(BaseModel):
    """The listener's certificate and the CA its clients' certificates must chain to."""

    model_config = _FROZEN

    cert_file: Path = Field(description="PEM server certificate (chain), with the key or not.")
    key_file: Path | None = Field(default=None, description="PEM key, if not in cert_file.")
    password_file: Path | None = Field(default=None, description="File holding the key password.")
    client_ca_file: Path = Field(description="Only clients with a certificate from this CA.")

    @model_validator(mode="after")
    def _loadable(self, info: ValidationInfo) -> NffiSourceTls:
        # On the node (check-config without --no-environment): the files must load, and the
        # error is then on this section's line, not only on the source's.
        if isinstance(info.context, dict) and info.context.get("environment"):
            _server_context(self)
        return self


class NffiSourceConfig(SourceConfig):
    """An IP1 listener: ``tcp://HOST:PORT`` or ``tls://HOST:PORT``, and who may connect."""

    type: Literal["nffi"] = Field(default="nffi", description="The source type.")
    name: str = Field(
        default="nffi",
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$",
        description="Named in metrics and /status.",
    )
    uri: str = Field(description="tcp://HOST:PORT or tls://HOST:PORT to listen on.")
    tls: NffiSourceTls | None = Field(default=None, description="Required for tls://.")
    allow: tuple[_AllowedNetwork, ...] = Field(
        min_length=1,
        description="Networks peers may connect from (e.g. 10.1.2.0/24); 0.0.0.0/0 is anyone.",
    )
    max_message_bytes: int = Field(
        default=262_144, ge=1024, le=MAX_MESSAGE_BYTES, description="Largest document read."
    )
    max_clients: int = Field(default=16, ge=1, description="Connections served at once.")
    idle_timeout_s: float = Field(default=300.0, gt=0, description="Close a silent connection.")
    handshake_timeout_s: float = Field(default=10.0, gt=0, description="TLS handshake deadline.")
    max_age_s: float = Field(
        default=600.0, gt=0, description="A track older than this is not a current position."
    )
    max_units: int = Field(default=10_000, ge=1, description="Units whose newest time is kept.")

    @field_validator("uri")
    @classmethod
    def _check_uri(cls, value: str) -> str:
        parts = urlsplit(value)
        try:
            port = parts.port
        except ValueError:
            port = None
        if parts.scheme not in ("tcp", "tls") or not parts.hostname or port is None:
            raise ValueError(f"expected tcp://HOST:PORT or tls://HOST:PORT, got {value!r}")
        return value

    @model_validator(mode="after")
    def _tls_with_tls(self) -> NffiSourceConfig:
        if self.uri.startswith("tls://") != (self.tls is not None):
            raise ValueError("a 'tls' section goes with a tls:// uri and only with it")
        return self


def _server_context(tls: NffiSourceTls) -> ssl.SSLContext:
    """TLS 1.2+ server context that demands a client certificate from ``client_ca_file``."""
    files = TlsFiles(tls.client_ca_file, tls.cert_file, tls.key_file, None, tls.password_file)
    if (problem := unreadable_file(files)) is not None:
        raise ValueError(problem)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.verify_mode = ssl.CERT_REQUIRED
    password = None
    if tls.password_file is not None:
        password = tls.password_file.read_bytes().rstrip(b"\r\n")
    try:
        context.load_cert_chain(
            str(tls.cert_file), None if tls.key_file is None else str(tls.key_file), password
        )
    except ssl.SSLError as exc:
        raise ValueError(
            f"{tls.cert_file}: cannot load the certificate and key ({exc.reason})"
        ) from None
    try:
        context.load_verify_locations(cafile=str(tls.client_ca_file))
    except ssl.SSLError as exc:
        raise ValueError(f"{tls.client_ca_file}: not a usable CA ({exc.reason})") from None
    return context


class NffiSource:
    """Listens for IP1 peers and publishes a ``BlueForce`` for each current friendly track."""

    config_model: ClassVar[type[NffiSourceConfig]] = NffiSourceConfig

    def __init__(
        self,
        name: str,
        config: NffiSourceConfig,
        publish: Callable[[Event], bool],
        *,
        clock: Callable[[], datetime] = utc_now,
    ) -> None:
        self.name = name
        self.config = config
        self._publish = publish
        self._clock = clock
        # Read the TLS files now: a missing file is a config error on this source's line.
        self._context = None if config.tls is None else _server_context(config.tls)
        #: ``authenticated`` on tls:// (a client certificate from ``client_ca_file``),
        #: ``address_only`` on tcp:// (the allow-list checks an address, not a sender).
        self.provenance = (
            Provenance.ADDRESS_ONLY if config.tls is None else Provenance.AUTHENTICATED
        )
        parts = urlsplit(config.uri)
        self.host, self.port = str(parts.hostname), int(parts.port or 0)
        #: Outcomes: tracks (accepted, stale, future, no_fix, not_friendly, older, duplicate,
        #: skipped), documents (invalid, oversize, fragment, empty), connections
        #: (not_allowed, tls_failed, idle_closed).
        self.counts: Counter[str] = Counter()
        #: Invalid documents and skipped tracks by problem (xml, dtd, root, dateTime, ...).
        self.problems: Counter[str] = Counter()
        self._newest = NewestTimes(config.max_units)
        self._log_limit = RateLimit(interval_s=LOG_INTERVAL_S)
        self.log = log.bind(source=name)
        self._listener = TcpListener(
            self.host, self.port, name=f"nffi source {name}", max_connections=config.max_clients
        )

    @property
    def local_port(self) -> int:
        """The bound port (after ``run`` has started)."""
        return self._listener.local_port

    def status(self) -> dict[str, object]:
        """What /status shows for this source."""
        return {
            "source": self.name,
            "type": "nffi",
            "uri": self.config.uri,
            "counts": dict(self.counts),
            "problems": dict(self.problems),
            "connections": self._listener.stats.status(),
        }

    def _count(self, outcome: str, **fields: object) -> None:
        self.counts[outcome] += 1
        if self._log_limit.allow(outcome):
            self.log.warning("nffi_input_rejected", outcome=outcome, **fields)

    # -- documents and tracks --------------------------------------------------------------

    def handle(self, data: bytes) -> bool:
        """Take one document; publish its current tracks, count the rest. Never raises.

        Returns True if it was an NFFI document (even one whose tracks were all refused).
        """
        try:
            message = parse_message(data, max_bytes=self.config.max_message_bytes)
        except NffiError as exc:
            self.problems[exc.problem] += 1
            self._count("oversize" if exc.problem == "oversize" else "invalid", problem=exc.problem)
            return False
        if not message.tracks and not message.skipped:
            self.counts["empty"] += 1  # a heartbeat
        for problem in message.skipped:
            self.problems[problem] += 1
            self._count("skipped", problem=problem)
        for track in message.tracks:
            self._take(track)
        return True

    def _take(self, track: NffiTrack) -> None:
        uid = track.uid
        now = self._clock()
        if track.time > now + FUTURE_TOLERANCE:
            self._count("future", uid=uid)
            return
        if track.time < now - timedelta(seconds=self.config.max_age_s):
            self._count("stale", uid=uid)
            return
        if abs(track.lat_deg) < _NO_FIX_DEG and abs(track.lon_deg) < _NO_FIX_DEG:
            self._count("no_fix", uid=uid)
            return
        if track.unit_symbol is not None and track.unit_symbol[1] in _NOT_FRIENDLY:
            self._count("not_friendly", uid=uid)
            return
        refusal = self._newest.refusal(uid, track.time)
        if refusal is not None:
            self._count(refusal, uid=uid)
            return
        self._newest.remember(uid, track.time)
        self.counts["accepted"] += 1
        self._publish(_blue_force(track, self.name, self.provenance))

    # -- connections -----------------------------------------------------------------------

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Listen, report started, and serve until cancelled. Bind errors raise ``OSError``."""
        self._listener.bind()
        task_status.started()
        await self._listener.run(self._serve)

    def _is_allowed(self, address: str) -> bool:
        try:
            ip = ipaddress.ip_address(address.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip.version == net.version and ip in net for net in self.config.allow)

    async def _serve(self, connection: Connection) -> None:
        if not self._is_allowed(connection.peer[0]):
            self._count("not_allowed", peer=connection.peer[0])
            return
        if self._context is None:
            await self._read(connection, connection.receive)
            return
        sock = await self._handshake(connection)
        if sock is None:
            return
        with sock:
            await self._read(connection, lambda n: _receive_tls(sock, n))

    async def _handshake(self, connection: Connection) -> ssl.SSLSocket | None:
        assert self._context is not None  # noqa: S101 - only for tls://
        sock = self._context.wrap_socket(
            connection.sock, server_side=True, do_handshake_on_connect=False
        )
        try:
            with anyio.fail_after(self.config.handshake_timeout_s):
                while True:
                    try:
                        sock.do_handshake()
                        return sock
                    except ssl.SSLWantReadError:
                        await anyio.wait_readable(sock)
                    except ssl.SSLWantWriteError:
                        await anyio.wait_writable(sock)
        except (TimeoutError, OSError) as exc:  # ssl.SSLError is an OSError
            sock.close()
            reason = "timeout" if isinstance(exc, TimeoutError) else type(exc).__name__
            self._count("tls_failed", peer=connection.peer[0], reason=reason)
            return None
        except BaseException:
            sock.close()
            raise

    async def _read(
        self, connection: Connection, receive: Callable[[int], Awaitable[bytes]]
    ) -> None:
        splitter = MessageSplitter(self.config.max_message_bytes)
        while True:
            try:
                with anyio.fail_after(self.config.idle_timeout_s):
                    chunk = await receive(65_536)
            except TimeoutError:
                self._count("idle_closed", peer=connection.peer[0])
                return
            except (anyio.EndOfStream, anyio.BrokenResourceError):
                return
            fragments = splitter.fragments
            for document in splitter.feed(chunk):
                if self.handle(document):
                    # A peer that sends documents keeps its place over idle strangers.
                    connection.trusted = True
            for _ in range(splitter.fragments - fragments):
                self._count("fragment")
            if splitter.is_overflowing:
                self._count("oversize", size=splitter.buffered)
                return


async def _receive_tls(sock: ssl.SSLSocket, max_bytes: int) -> bytes:
    """At most ``max_bytes`` of plaintext; ``anyio.EndOfStream`` when the peer has closed."""
    while True:
        try:
            data = sock.recv(max_bytes)
        except ssl.SSLWantReadError:
            await anyio.wait_readable(sock)
            continue
        except ssl.SSLWantWriteError:
            await anyio.wait_writable(sock)
            continue
        except (ssl.SSLZeroReturnError, ssl.SSLEOFError):
            raise anyio.EndOfStream from None
        except OSError as exc:
            raise anyio.BrokenResourceError(str(exc)) from exc
        if not data:
            raise anyio.EndOfStream
        return data


def _blue_force(track: NffiTrack, source_name: str, provenance: Provenance) -> BlueForce:
    return BlueForce(
        event_id=event_id("nffi", track.uid, int(track.time.timestamp())),
        uid=track.uid,
        time=track.time,
        callsign=safe_text(track.unit_short_name or track.transponder_id),
        position=Position(lat_deg=track.lat_deg, lon_deg=track.lon_deg, alt_msl_m=track.alt_msl_m),
        source="nffi",
        source_name=source_name,
        provenance=provenance,
        course_deg=track.bearing_deg,
        speed_mps=track.speed_mps,
        sidc=track.unit_symbol,
    )
