"""The CoT sink: own airframes, detections and tracks to ATAK/WinTAK/iTAK and TAK servers.

Relayed friendly units (``blue_force``, e.g. from the NFFI source) are sent too when a route
gives them to the sink (not by default): with their own uid, a friendly type from their SIDC
(``a-f-G`` without one), ``how="h-e"`` and ``stale.blue_force_s``. Do not route the CoT
source's blue force back to the mesh it came from: ATAK devices already see each other.

Destinations are URIs: ``udp://`` (unicast, or multicast when the address is a group) and
``udp+multicast://`` (ATAK's SA mesh is ``udp+multicast://239.2.3.1:6969``; ``?ttl=`` and
``?iface=`` set TTL and interface), ``tcp://HOST:8087`` and ``tls://HOST:8089`` (a TAK server
stream; TLS with a client certificate, the CA pinned and the hostname always verified). The
encoding is ``xml``, ``protobuf`` (TAK protocol v1: mesh framing on UDP, stream framing on TCP)
or ``negotiate`` (streams: XML until the server offers v1 and accepts our request; UDP: XML).
Each event is built once and encoded at most once per encoding, whatever the destinations,
and once for all the CoT sinks whose options and airframe types are the same
(``sinks.cot.shared``).
Mesh protobuf destinations advertise TAK protocol v1 (``TakControl``) at least every
``takcontrol_interval_s`` from the sink's ``run`` lifetime, which its SinkRunner starts.
``contact`` carries no ``endpoint``: ``*:-1:stcp`` is only right on a TAK server stream, and
an event is built once for every destination, so it is left out everywhere (``cot.md`` §5).

Tracks are sent on change: a track whose CoT content is unchanged since it was last delivered
is not re-sent until ``track_refresh_s`` (default half its stale time) has passed. Beyond that
the sink keeps no delivery state: a failure raises ``TransientSinkError`` naming the sink and
the destination, and the SinkRunner retries the batch with its jittered backoff (CoT receivers
replace by uid, so a destination that already had the batch shrugs off the repeat). One sink
backs off as a whole; give a flaky TAK server its own sink so the mesh does not wait for it.

A sink whose destinations are all UDP also has ``send_now`` (``gateway.c2.sink.SendsNow``):
its runner sends each ready batch in the loop pass's delivery pass, datagram by datagram
straight to the non-blocking sockets, and hands ``send`` the events from the first one a
socket could not take at once.
"""

from __future__ import annotations

import ssl
from collections.abc import Callable, Sequence
from datetime import datetime, timedelta
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, Literal
from urllib.parse import parse_qs, urlsplit

import anyio
import anyio.abc
import structlog
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from gateway.c2.sink import SinkConfig
from gateway.domain.geoid import GeoidGrid, bundled_geoid
from gateway.domain.symbols import load_tables
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import Event, EventKind, Track
from gateway.ops.logsetup import RateLimit
from gateway.transports.tls import TlsFiles, tls_context
from gateway.transports.udp import is_multicast
from sinks.cot.codec import Encoded
from sinks.cot.event import CotOptions, StaleTimes, own_uid
from sinks.cot.shared import SHARED, AirframeTypes, SharedBuilds
from sinks.cot.transport import Endpoint, StreamConnection
from sinks.cot.udp import UdpSender

__all__ = ["CotDestination", "CotSink", "CotSinkConfig", "CotStale", "CotTls"]

log = structlog.get_logger(__name__)

CotProtocol = Literal["xml", "protobuf", "negotiate"]
_FROZEN = ConfigDict(frozen=True, extra="forbid")
#: Delivered tracks older than their stale time are forgotten at most this often: an entry
#: that old is news anyway (``track_refresh_s`` < stale), so only memory waits for it.
_FORGET_EVERY = timedelta(seconds=10)
_SCHEMES = ("udp", "udp+multicast", "tcp", "tls")
_ACCEPTED_KINDS = frozenset(
    {
        EventKind.TELEMETRY,
        EventKind.DETECTION,
        EventKind.TRACK,
        EventKind.LINK_STATE,
        EventKind.BLUE_FORCE,
    }
)


class CotTls(BaseModel):
    """The client certificate (PEM pair or PKCS#12) and the pinned CA of a TAK server."""

    model_config = _FROZEN

    ca_file: Path = Field(description="The only CA trusted for the server's certificate.")
    cert_file: Path | None = Field(default=None, description="PEM client certificate (chain).")
    key_file: Path | None = Field(default=None, description="PEM key, if not in cert_file.")
    pkcs12_file: Path | None = Field(default=None, description="Client key and certificate.")
    password_file: Path | None = Field(
        default=None, description="File holding the key's or PKCS#12 password (never inline)."
    )
    server_hostname: str | None = Field(
        default=None, description="Name the certificate must carry; defaults to the URI host."
    )

    @model_validator(mode="after")
    def _one_client_certificate(self, info: ValidationInfo) -> CotTls:
        if (self.cert_file is None) == (self.pkcs12_file is None):
            raise ValueError("give exactly one of cert_file (PEM) or pkcs12_file")
        if self.key_file is not None and self.cert_file is None:
            raise ValueError("key_file goes with cert_file")
        if isinstance(info.context, dict) and info.context.get("environment"):
            # On the node (run, check-config): load the files now, so a missing CA or a
            # wrong PKCS#12 password is a config error with its line, not a retry loop.
            files = TlsFiles(
                self.ca_file, self.cert_file, self.key_file, self.pkcs12_file, self.password_file
            )
            try:
                tls_context(files)
            except (OSError, ssl.SSLError) as exc:
                name = getattr(exc, "filename", None) or files.ca_file
                raise ValueError(f"{name}: {getattr(exc, 'strerror', None) or exc}") from None
        return self


class CotDestination(BaseModel):
    """One place CoT goes. A plain string in the config is taken as the ``uri``."""

    model_config = _FROZEN

    uri: str = Field(
        description="udp://HOST:PORT (unicast or multicast), tcp://HOST:PORT or tls://HOST:PORT."
    )
    protocol: CotProtocol | None = Field(default=None, description="Overrides the sink's.")
    ttl: int | None = Field(default=None, ge=1, le=255, description="Multicast TTL (1).")
    interface: str | None = Field(default=None, description="Multicast interface: IP or name.")
    tls: CotTls | None = Field(
        default=None, description="Client certificate and pinned CA; required for tls://."
    )

    @model_validator(mode="before")
    @classmethod
    def _from_string(cls, value: Any) -> Any:
        return {"uri": value} if isinstance(value, str) else value

    @model_validator(mode="after")
    def _check(self) -> CotDestination:
        parts = urlsplit(self.uri)
        try:
            port = parts.port
        except ValueError:
            port = None
        if parts.scheme not in _SCHEMES or not parts.hostname or not port:
            raise ValueError(
                f"expected udp://, udp+multicast://, tcp:// or tls://HOST:PORT, got {self.uri!r}"
            )
        query = parse_qs(parts.query, strict_parsing=False)
        udp = parts.scheme.startswith("udp")
        if set(query) - {"ttl", "iface"} or (query and not udp):
            raise ValueError(f"{self.uri!r}: only udp URIs take query options, ttl and iface")
        if parts.scheme == "udp+multicast" and not is_multicast(parts.hostname):
            raise ValueError(f"{self.uri!r}: {parts.hostname} is not a multicast group")
        if (parts.scheme == "tls") != (self.tls is not None):
            raise ValueError(f"{self.uri!r}: a 'tls' section goes with tls:// and only with it")
        if udp and self.protocol == "negotiate":
            raise ValueError(f"{self.uri!r}: negotiate is for tcp:// and tls://")
        return self

    def endpoint(self, default_protocol: CotProtocol) -> Endpoint:
        """The transport's view of this destination."""
        parts = urlsplit(self.uri)
        query = parse_qs(parts.query)
        protocol = self.protocol or default_protocol
        scheme: Literal["udp", "udp+multicast", "tcp", "tls"] = parts.scheme  # type: ignore[assignment]
        if scheme.startswith("udp") and protocol == "negotiate":
            protocol = "xml"  # mesh peers negotiate by advertising; we stay on what all read
        ttl = self.ttl or int(query.get("ttl", ["1"])[-1])
        tls = self.tls
        return Endpoint(
            uri=self.uri,
            scheme=scheme,
            host=str(parts.hostname),
            port=int(parts.port or 0),
            protocol=protocol,
            ttl=ttl,
            interface=self.interface or query.get("iface", [None])[-1],
            tls=None
            if tls is None
            else TlsFiles(
                tls.ca_file, tls.cert_file, tls.key_file, tls.pkcs12_file, tls.password_file
            ),
            server_hostname=None if tls is None else tls.server_hostname,
        )

    @field_validator("uri")
    @classmethod
    def _no_credentials(cls, value: str) -> str:
        if urlsplit(value).password is not None:
            raise ValueError("no passwords in URIs; use tls.password_file")
        return value


class CotStale(BaseModel):
    """How long each kind stays valid on the receivers' maps, in seconds."""

    model_config = _FROZEN

    telemetry_s: float = Field(default=15.0, ge=1.0, description="Own airframes.")
    detection_s: float = Field(default=120.0, ge=1.0, description="Single detections.")
    track_s: float = Field(default=300.0, ge=1.0, description="Fused tracks.")
    blue_force_s: float = Field(
        default=600.0, ge=1.0, description="Relayed friendly units (blue_force)."
    )


def _uri_strings_too(schema: dict[str, Any]) -> None:
    # A destination may be written as its URI alone (CotDestination's before-validator).
    items = schema.get("items")
    if isinstance(items, dict):
        schema["items"] = {"anyOf": [{"type": "string"}, items]}


class CotSinkConfig(SinkConfig):
    """Options of the CoT sink."""

    destinations: tuple[CotDestination, ...] = Field(
        min_length=1,
        description="Where CoT goes; each a URI or a mapping with uri.",
        json_schema_extra=_uri_strings_too,
    )
    protocol: CotProtocol = Field(
        default="xml", description="xml, protobuf (TAK v1) or negotiate (TAK servers)."
    )
    kinds: frozenset[EventKind] = Field(
        default=frozenset({EventKind.TELEMETRY, EventKind.DETECTION, EventKind.TRACK}),
        description="Event kinds this sink takes.",
    )
    stale: CotStale = Field(default=CotStale(), description="Seconds each kind stays valid.")
    track_refresh_s: float | None = Field(
        default=None, gt=0, description="Re-send an unchanged track after this (stale / 2)."
    )
    uid_prefix: str = Field(
        default="fischer-", pattern=r"^\S*$", description="Start of every event uid we send."
    )
    callsign_prefix: str = Field(default="FISCHER ", description="Start of own callsigns.")
    loitering_munition: Literal["uav_attack", "missile"] = Field(
        default="uav_attack", description="How a loitering munition is drawn (2525 symbol)."
    )
    detection_hostility: Literal["hostile", "suspect", "unknown"] = Field(
        default="hostile", description="Affiliation given to detected targets."
    )
    group_name: str | None = Field(
        default=None, description="ATAK team colour for own airframes (e.g. Cyan); none if unset."
    )
    group_role: str = Field(default="Team Member", description="ATAK role of own airframes.")
    geoid_file: Path | None = Field(
        default=None, description="EGM96 .gtx grid for hae (default: the shipped 30' grid)."
    )
    connect_timeout_s: float = Field(
        default=5.0, gt=0, description="Deadline of a TCP/TLS connect."
    )
    offer_wait_s: float = Field(
        default=2.0, ge=0, description="After connecting, wait this long for a v1 offer."
    )
    response_wait_s: float = Field(
        default=60.0, gt=0, description="Wait this long for the TakResponse (spec: ≥ 60 s)."
    )
    takcontrol_interval_s: float = Field(
        default=30.0,
        gt=0,
        le=60,
        description="Mesh protobuf: advertise TAK protocol v1 this often (spec: ≤ 60 s).",
    )

    @field_validator("kinds")
    @classmethod
    def _known_kinds(cls, value: frozenset[EventKind]) -> frozenset[EventKind]:
        if extra := value - _ACCEPTED_KINDS:
            raise ValueError(
                f"the cot sink takes telemetry, detection, track and blue_force, not {extra}"
            )
        return value


def _package_version() -> str:
    try:
        return version("fischer-gateway")
    except PackageNotFoundError:
        return "0"


class CotSink:
    """Sends own airframes, detections and tracks as CoT to every configured destination."""

    config_model = CotSinkConfig

    def __init__(self, name: str, config: CotSinkConfig, *, builds: SharedBuilds = SHARED) -> None:
        self.name = name
        self.config = config
        geoid = GeoidGrid.from_gtx(config.geoid_file) if config.geoid_file else bundled_geoid()
        stale = config.stale
        self.options = CotOptions(
            uid_prefix=config.uid_prefix,
            callsign_prefix=config.callsign_prefix,
            stale=StaleTimes(
                stale.telemetry_s, stale.detection_s, stale.track_s, stale.blue_force_s
            ),
            loitering_munition=config.loitering_munition,
            detection_hostility=config.detection_hostility,
            geoid=geoid.undulation,
            group=(config.group_name, config.group_role) if config.group_name else None,
            version=_package_version(),
        )
        # Sinks with equal options share their builds (``sinks.cot.shared``).
        self._builds = builds
        self.options = builds.canonical(self.options)
        self._refresh = timedelta(seconds=config.track_refresh_s or stale.track_s / 2)
        #: A CoT source hearing our own reports back (a mesh echo, a TAK server relaying
        #: everything, or a forgery) must not make our airframes friendly units: the gateway
        #: refuses a source's report under these uids (``gateway.c2.sink.ReleasesOwnAirframes``).
        self._transports: list[UdpSender | StreamConnection] = []
        for dest in config.destinations:
            endpoint = dest.endpoint(config.protocol)
            if endpoint.scheme.startswith("udp"):
                sender = UdpSender(endpoint, name, announce_every_s=config.takcontrol_interval_s)
                self._transports.append(sender)
            else:
                self._transports.append(
                    StreamConnection(
                        endpoint,
                        name,
                        connect_timeout_s=config.connect_timeout_s,
                        offer_wait_s=config.offer_wait_s,
                        response_wait_s=config.response_wait_s,
                    )
                )
        udp = tuple(t for t in self._transports if isinstance(t, UdpSender))
        self._udp = udp if len(udp) == len(self._transports) else ()
        #: ``SendsNow``, offered only when every destination is UDP (a stream may block).
        self.send_now: Callable[[Sequence[Event]], int] | None = (
            self._send_now if self._udp else None
        )
        self._own_types = AirframeTypes()
        #: Mesh TakControl announcements the network refused.
        self.announce_failures = 0
        self._log_limit = RateLimit(interval_s=30.0)
        # Per track uid: its CoT content when last delivered, and that event's time.
        self._delivered: dict[str, tuple[tuple[object, ...], datetime]] = {}
        self._forgot_at: datetime | None = None

    def own_uids(self, airframes: Sequence[str]) -> frozenset[str]:
        """The uids our own airframes' CoT carries, which a CoT source would read back."""
        return frozenset(own_uid(self.options.uid_prefix, airframe) for airframe in airframes)

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Telemetry, detections and tracks unless the config narrows it."""
        return self.config.kinds

    async def open(self) -> None:
        """Open every destination; ``TransientSinkError`` (retried) if one cannot be reached."""
        load_tables()  # the symbol tables, before the first event rather than at it
        for transport in self._transports:
            await self._call(transport, None)

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """The sink's lifetime (started by its SinkRunner): keep the mesh told we speak v1.

        Every mesh protobuf destination gets a ``TakControl`` at least every
        ``takcontrol_interval_s``, riding on an event or, when none went out, on its own.
        A network error here is counted and logged (rate-limited); ``send`` reports it.
        """
        mesh = [t for t in self._transports if isinstance(t, UdpSender) and t.encoding == "mesh"]
        task_status.started()
        if not mesh:
            return
        while True:
            for sender in mesh:
                try:
                    await sender.announce()
                except OSError as exc:
                    self.announce_failures += 1
                    if self._log_limit.allow(sender.endpoint.uri):
                        log.warning(
                            "cot_announcement_failed",
                            sink=self.name,
                            destination=sender.endpoint.uri,
                            error=str(exc),
                            failures=self.announce_failures,
                        )
            # Never sooner than 50 ms: a failing sender is retried, not spun on.
            await anyio.sleep(max(0.05, min(s.announce_due_in_s() for s in mesh)))

    async def _call(
        self, transport: UdpSender | StreamConnection, events: list[Encoded] | None
    ) -> None:
        if isinstance(transport, StreamConnection):
            await (transport.open() if events is None else transport.send(events))
            return
        try:
            await (transport.open() if events is None else transport.send(events))
        except OSError as exc:
            await transport.aclose()
            raise TransientSinkError(
                f"sink {self.name}: {transport.endpoint.uri}: {exc}", sink=self.name
            ) from exc

    def _is_news(self, cot_uid: str, content: tuple[object, ...], time: datetime) -> bool:
        last = self._delivered.get(cot_uid)
        return last is None or last[0] != content or not time - last[1] < self._refresh

    async def send(self, batch: Sequence[Event]) -> None:
        """Build each event once and deliver it to every destination, or raise.

        An event too large for one UDP datagram is sent where it fits and refused by id
        (``PermanentSinkError(event_ids=...)``) after the rest of the batch was delivered.
        """
        events: list[Encoded] = []
        ids: dict[int, str] = {}
        tracks: dict[str, tuple[tuple[object, ...], datetime]] = {}
        for event in batch:
            encoded = self._builds.encoded(event, self.options, self._own_types)
            if encoded is None:
                continue
            cot = encoded.event
            if isinstance(event, Track):
                content = cot.content()
                if not self._is_news(cot.uid, content, event.time):
                    continue
                tracks[cot.uid] = (content, event.time)
            ids[id(encoded)] = event.event_id
            events.append(encoded)
        if not events:
            return
        oversize: set[str] = set()
        for transport in self._transports:
            if isinstance(transport, UdpSender):
                oversize.update(ids[id(e)] for e in transport.oversize(events))
            await self._call(transport, events)
        # Only now: a failed batch is retried whole, its tracks included.
        if tracks:
            self._delivered.update(tracks)
            self._forget_old_tracks(max(time for _, time in tracks.values()))
        if oversize:
            raise PermanentSinkError(
                f"sink {self.name}: {len(oversize)} event(s) larger than one UDP datagram",
                sink=self.name,
                event_ids=oversize,
            )

    def _send_now(self, batch: Sequence[Event]) -> int:
        """``send`` for UDP destinations without an await: how many leading events went out.

        Stops before the first event a socket cannot take at once, or that is too large or
        due a ``TakControl``: ``send`` delivers (or refuses) it and the rest.
        """
        senders = self._udp
        tracks: dict[str, tuple[tuple[object, ...], datetime]] = {}
        done = 0
        for event in batch:
            encoded = self._builds.encoded(event, self.options, self._own_types)
            track: tuple[str, tuple[tuple[object, ...], datetime]] | None = None
            if encoded is not None and isinstance(event, Track):
                cot = encoded.event
                content = cot.content()
                if self._is_news(cot.uid, content, event.time):
                    track = (cot.uid, (content, event.time))
                else:
                    encoded = None  # unchanged since delivered: not re-sent yet
            if encoded is not None:
                if not all(sender.send_now(encoded) for sender in senders):
                    break
                if track is not None:
                    tracks[track[0]] = track[1]
            done += 1
        if tracks:
            self._delivered.update(tracks)
            self._forget_old_tracks(max(time for _, time in tracks.values()))
        return done

    def _forget_old_tracks(self, now: datetime) -> None:
        # A scan of every track delivered: at most once per _FORGET_EVERY of track time.
        if self._forgot_at is not None and now - self._forgot_at < _FORGET_EVERY:
            return
        self._forgot_at = now
        horizon = now - timedelta(seconds=self.config.stale.track_s)
        for uid in [u for u, (_, sent) in self._delivered.items() if sent < horizon]:
            del self._delivered[uid]

    async def aclose(self) -> None:
        """Close every destination. Safe after a failed ``open``."""
        for transport in self._transports:
            await transport.aclose()
