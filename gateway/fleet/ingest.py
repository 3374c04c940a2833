"""From bytes on a link to events on the bus: authenticate, parse, demultiplex, de-duplicate.

``Ingest.on_data`` is the per-chunk hot path. It is synchronous and never raises: bytes that
do not authenticate or parse are counted by reason and logged (rate-limited: at most one
line per link and reason every ``REJECT_LOG_INTERVAL_S``).

A frame is attributed to an airframe only when it arrives on a link *configured for that
airframe* and passes that link's security: on a tunnel link the key that sealed it names
the airframe; on a signed link the airframe's signing key must verify it; on an unsecured
link its sysid must be one of the airframes configured on that link. Anything else is
counted with a reason (``foreign_link``, ``unknown_sysid``, ``auth`` ...) and dropped; no
link is ever added to an airframe at run time. The peer that last authenticated for an
airframe on a link is remembered, and it is the only peer uplink traffic goes to
(``peer_for``). A frame that already arrived on another link of the same airframe is
delivered once. What is left becomes Telemetry, goes to the airframe's passthrough if it has
one, and updates link health (``linkhealth``). Telemetry snapshots are coalesced per pass of
the event loop (see ``flush``).

State per sender is bounded: a datagram link keeps one parser for the whole link (each
datagram is parsed on its own), a stream link one per connection (the listener caps them).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass, field
from functools import partial
from time import time_ns

import structlog

from gateway.clock import Clock, utc_now
from gateway.config import AirframeConfig
from gateway.domain.terrain import TerrainModel
from gateway.errors import FrameError
from gateway.events import Event, VideoFrameMetadata
from gateway.fleet.acks import DetectionAcks, DetectionLedger
from gateway.fleet.deframe import StreamDeframer
from gateway.fleet.linkhealth import LinkHealth
from gateway.fleet.mavlink import MavlinkParser, MavMessage
from gateway.fleet.normalise import (
    NORMALISED_TYPES,
    AirframeState,
    Enrichment,
    detection_from,
)
from gateway.fleet.security.signing import SigningVerifier
from gateway.fleet.security.tunnel import Opened, TunnelOpener
from gateway.fleet.session import AirframeSession, Transmit
from gateway.fleet.video import CameraView
from gateway.ops.instruments import Instruments
from gateway.ops.logsetup import RateLimit
from gateway.ops.metrics import CounterChild, HistogramChild

__all__ = ["Ingest", "LinkIntake"]

log = structlog.get_logger(__name__)

#: Seconds between two log lines for the same link and rejection reason.
REJECT_LOG_INTERVAL_S = 10.0
_STX_V2 = 0xFD
#: Tunnel frames in a row that fail authentication before a stream peer is hung up on.
MAX_FAILED_IN_A_ROW = 64


@dataclass(slots=True)
class LinkIntake:
    """How bytes from one link endpoint are read: security mode, framing, per-peer state."""

    label: str
    security: str
    is_stream: bool
    max_chunk_bytes: int = 2048
    parsers: dict[object, MavlinkParser] = field(default_factory=dict)
    deframers: dict[object, StreamDeframer] = field(default_factory=dict)
    counters: tuple[CounterChild, CounterChild, CounterChild] | None = None
    airframes: dict[int, AirframeSession] = field(default_factory=dict)
    """The airframes configured on this link, by sysid: the only ones it may speak for."""
    datagram_parser: MavlinkParser | None = None
    sealed: dict[str, tuple[AirframeSession, HistogramChild]] = field(default_factory=dict)
    """Per airframe id that a tunnel key on this link named: its session and latency histogram."""
    trust: Callable[[object], None] | None = None
    """Told the first time a peer authenticates for an airframe (a listener keeps it)."""
    drop: Callable[[object], None] | None = None
    """Told to hang up on a stream peer that only sends frames that fail authentication."""


class Ingest:
    """Authenticates and parses link bytes, and routes frames to their airframe's state."""

    def __init__(
        self,
        airframes: Iterable[AirframeConfig],
        publish: Callable[[Event], bool],
        instruments: Instruments,
        clock: Clock,
        *,
        opener: TunnelOpener | None = None,
        verifiers: Mapping[int, SigningVerifier] | None = None,
        terrain: TerrainModel | None = None,
        baro_sigma_m: float = 0.5,
        ledger: DetectionLedger | None = None,
        transmit: Transmit | None = None,
    ) -> None:
        self._publish = publish
        #: Durable intake of detections with acknowledgements, when there is a spool.
        self.acks = None if ledger is None else DetectionAcks(publish, ledger, instruments)
        self._inst = instruments
        self._opener = opener
        self._clock = clock
        #: The clock in milliseconds since 1970 (UTC), read once per datagram on a tunnel link;
        #: None when the clock is the wall clock, whose own reading is taken instead (a
        #: datetime per frame costs four times as much).
        self._now_ms: Callable[[], int] | None = (
            None if clock is utc_now else lambda: int(clock().timestamp() * 1000)
        )
        self._by_sysid: dict[int, AirframeSession] = {}
        self._by_id: dict[str, AirframeSession] = {}
        for cfg in airframes:
            enrichment = Enrichment(cfg.energy, cfg.ew_mode, terrain, baro_sigma_m)
            state = AirframeState(cfg.id, clock, enrichment)
            health = LinkHealth(cfg, publish, clock, instruments, on_active=state.set_active_link)
            labels = frozenset(link.label for link in cfg.links)
            verifier = (verifiers or {}).get(cfg.sysid)
            airframe = AirframeSession(cfg, state, health, labels, verifier, transmit=transmit)
            for name in NORMALISED_TYPES:
                airframe.on(name, self._telemetry_handler(state.updater(name), cfg.id))
            airframe.on("FISCHER_DETECTION", self._detection)
            airframe.on("COMMAND_ACK", airframe.on_command_ack)
            view = CameraView(cfg.id, state, clock, terrain)
            airframe.on("CAMERA_FOV_STATUS", partial(self._video, view.camera_fov))
            airframe.on("GIMBAL_DEVICE_ATTITUDE_STATUS", partial(self._video, view.gimbal_attitude))
            self._by_sysid[cfg.sysid] = airframe
            self._by_id[cfg.id] = airframe
        self._intakes: dict[str, LinkIntake] = {}
        self._unknown_sysids: set[int] = set()
        self._dirty: dict[str, AirframeSession] = {}
        self._flush_pending = False
        self._reject_log = RateLimit(interval_s=REJECT_LOG_INTERVAL_S)

    def register_link(self, intake: LinkIntake) -> None:
        """Declare a link endpoint before it delivers data."""
        label = intake.label
        inst = self._inst
        intake.counters = (
            inst.link_bytes.labels(label),
            inst.link_chunks.labels(label),
            inst.link_frames.labels(label),
        )
        intake.airframes = {a.config.sysid: a for a in self._by_sysid.values() if label in a.labels}
        if not intake.is_stream:
            intake.datagram_parser = MavlinkParser(
                max_chunk_bytes=intake.max_chunk_bytes, fast=True
            )
        self._intakes[label] = intake

    def set_passthrough(self, airframe: str, forward: Callable[[bytes], None]) -> None:
        """Forward every accepted frame of ``airframe`` (raw MAVLink) to ``forward``."""
        self._by_id[airframe].set_passthrough(forward)

    def forget_peer(self, label: str, peer: object) -> None:
        """Drop the per-peer state of a closed stream connection."""
        intake = self._intakes.get(label)
        if intake is None:
            return
        intake.deframers.pop(peer, None)
        for key in [k for k in intake.parsers if k == peer or (type(k) is tuple and k[0] == peer)]:
            del intake.parsers[key]
        for airframe in intake.airframes.values():
            airframe.forget_peer(label, peer)

    def on_data(self, label: str, peer: object, data: bytes) -> None:
        """Take one datagram or stream read from link ``label``; never raises.

        The detections it carries are committed to the spool together when it is read, and
        only then acknowledged to their airframes.
        """
        try:
            self._on_data(label, peer, data)
        finally:
            if self.acks is not None and self.acks.is_open:
                self.acks.commit()

    def _on_data(self, label: str, peer: object, data: bytes) -> None:
        intake = self._intakes.get(label)
        if intake is None or intake.counters is None:
            return  # not a registered link: nothing to attribute it to
        counters = intake.counters
        counters[0].value += len(data)
        counters[1].value += 1
        if intake.security != "tunnel":
            if not data:
                self._rejected(label, "malformed", "empty datagram")
                return
            for msg in self._parse(intake, peer, data):
                self._frame(intake, peer, msg, None)
            return
        opener = self._opener
        if opener is None:
            self._rejected(label, "auth", "tunnel link without a tunnel key")
            return
        if not intake.is_stream:
            # One datagram, one tunnel frame: the common case, without the stream's list.
            now_ms = time_ns() // 1_000_000 if self._now_ms is None else self._now_ms()
            try:
                frame = opener.open_frame(data, label, now_ms)
            except FrameError as exc:
                self._rejected(label, exc.reason, str(exc))
                return
            self._opened(intake, peer, frame, now_ms)
            return
        deframer = intake.deframers.get(peer)
        if deframer is None:
            deframer = intake.deframers[peer] = StreamDeframer(intake.max_chunk_bytes)
        before = dict(deframer.errors)
        opened = deframer.feed(data, lambda frame: opener.open_frame(frame, label))
        for reason, count in deframer.errors.items():
            if count != before.get(reason, 0):
                self._rejected(label, reason, "tunnel frame", count - before.get(reason, 0))
        if deframer.failed_in_a_row >= MAX_FAILED_IN_A_ROW and intake.drop is not None:
            # Each try costs an AES-GCM open: a peer that never authenticates is cut off.
            deframer.failed_in_a_row = 0
            intake.drop(peer)
        if opened:
            now_ms = time_ns() // 1_000_000 if self._now_ms is None else self._now_ms()
            for frame in opened:
                self._opened(intake, peer, frame, now_ms)

    def _opened(self, intake: LinkIntake, peer: object, frame: Opened, now_ms: int) -> None:
        """One authenticated tunnel frame from ``peer``: its MAVLink frames, for its airframe."""
        label = intake.label
        sealed_by, payload, _day, sent_ms = frame
        sealed = intake.sealed.get(sealed_by)
        if sealed is None:
            airframe = self._by_id.get(sealed_by)
            if airframe is None or label not in airframe.labels:
                # A valid key, but this link is not one of that airframe's links.
                self._rejected(label, "foreign_link", f"{sealed_by} is not configured here")
                return
            # Bounded: the airframes configured on this link.
            histogram = self._inst.link_latency.labels(sealed_by, label)
            sealed = intake.sealed[sealed_by] = (airframe, histogram)
        airframe, histogram = sealed
        latency_s = (now_ms - sent_ms) / 1000.0
        histogram.observe(latency_s if latency_s > 0.0 else 0.0)
        airframe.health.latency(label, latency_s)
        # The key authenticated the datagram, so the sender is this airframe's peer.
        key = sealed_by if not intake.is_stream else (peer, sealed_by)
        for msg in self._parse(intake, key, payload):
            self._frame(intake, peer, msg, airframe)

    def _parse(self, intake: LinkIntake, peer: object, data: bytes) -> list[MavMessage]:
        parser = intake.datagram_parser
        if parser is None:
            parser = intake.parsers.get(peer)
            if parser is None:
                parser = MavlinkParser(max_chunk_bytes=intake.max_chunk_bytes)
                intake.parsers[peer] = parser
        bad, unknown, truncated = parser.bad, parser.unknown, parser.truncated
        try:
            messages = parser.feed(data, whole=intake.datagram_parser is not None)
        except FrameError as exc:
            self._rejected(intake.label, exc.reason, str(exc))
            return []
        label = intake.label
        if parser.bad != bad:
            # A datagram is one unit for the sender: it is counted once, however many bad
            # runs pymavlink found in it (and any cut-off frame at its end is part of that).
            count = 1 if intake.datagram_parser is not None else parser.bad - bad
            self._rejected(label, "malformed", "bad MAVLink frame", count)
        elif parser.truncated != truncated:
            self._rejected(label, "truncated", "datagram ended inside a frame")
        if parser.unknown != unknown and (
            (parser.bad == bad and parser.truncated == truncated) or intake.datagram_parser is None
        ):
            # In a datagram already counted as bad, an unknown id is part of the same garbage.
            self._inst.link_ignored.labels(label, "unknown_msgid").inc(parser.unknown - unknown)
        return messages

    def _frame(
        self, intake: LinkIntake, peer: object, msg: MavMessage, sealed_by: AirframeSession | None
    ) -> None:
        label = intake.label
        buf = msg.get_msgbuf()
        sysid = buf[5] if buf[0] == _STX_V2 else buf[3]  # the header's system id
        airframe = intake.airframes.get(sysid)
        if airframe is None:
            if sysid in self._by_sysid:
                # A configured airframe's sysid on a link not configured for it: impersonation
                # or a wiring mistake, and never attributed either way.
                self._rejected(label, "foreign_link", f"sysid {sysid} is not configured here")
            else:
                self._inst.link_ignored.labels(label, "unknown_sysid").inc()
                if len(self._unknown_sysids) < 256 and sysid not in self._unknown_sysids:
                    self._unknown_sysids.add(sysid)
                    log.info("unknown_sysid_heard", link=label, sysid=sysid)
            return
        if sealed_by is not None and sealed_by is not airframe:
            # A tunnel key proves who sealed the frame: it may not speak for another sysid.
            self._rejected(label, "auth", f"{sealed_by.config.id} sent frames as sysid {sysid}")
            return
        authenticated = True
        if intake.security == "signed":
            verifier = airframe.verifier
            if verifier is None:
                self._rejected(label, "auth", f"{airframe.config.id} has no signing key")
                return
            try:
                # False: an unsigned frame the config accepts (accept_unsigned_msgids). It is
                # used, but proves nothing: it neither names the peer nor keeps the link up.
                authenticated = verifier.verify(bytes(buf))
            except FrameError as exc:
                self._rejected(label, exc.reason, str(exc))
                return
        intake.counters[2].value += 1  # type: ignore[index]
        now_mono = time.monotonic()
        name = msg.get_type()
        if not airframe.accept(label, peer, authenticated, intake.trust, buf, name, msg, now_mono):
            self._inst.link_ignored.labels(label, "duplicate").inc()
            return
        try:
            airframe.dispatch(label, name, msg)
        except Exception:
            # A handler is an extension point (session.on): its bug costs this message only.
            self._inst.link_ignored.labels(label, "handler_error").inc()
            if self._reject_log.allow((label, "handler_error")):
                log.exception(
                    "message_handler_failed", link=label, airframe=airframe.id, message=name
                )

    def _telemetry_handler(
        self, update: Callable[[MavMessage], bool], airframe_id: str
    ) -> Callable[[AirframeSession, str, MavMessage], None]:
        """The handler of one telemetry message type of one airframe (``update`` merges it)."""

        def telemetry(airframe: AirframeSession, _label: str, msg: MavMessage) -> None:
            # The state's updater and the airframe's id are bound here: this runs for most
            # frames, so it reads nothing it does not need.
            if update(msg):
                self._dirty[airframe_id] = airframe
                if not self._flush_pending:
                    self._schedule_flush()

        return telemetry

    def _detection(self, airframe: AirframeSession, label: str, msg: MavMessage) -> None:
        # Detections are durable: published at once, never coalesced like telemetry.
        detection = detection_from(airframe.config.id, msg, self._clock())
        if detection is None:
            self._rejected(label, "malformed", "FISCHER_DETECTION with impossible values")
            return
        if self.acks is None:
            self._publish(detection)
        else:
            self.acks.take(airframe, label, detection, int(msg.detection_id), int(msg.time_usec))

    def _video(
        self,
        take: Callable[[MavMessage], VideoFrameMetadata | None],
        _airframe: AirframeSession,
        _label: str,
        msg: MavMessage,
    ) -> None:
        # Latest-wins like telemetry, but one event per camera report: each describes a frame.
        event = take(msg)
        if event is not None:
            self._publish(event)

    def _schedule_flush(self) -> None:
        # Telemetry is latest-wins, so the frames read in one pass of the event loop make one
        # snapshot per airframe: under load the work per frame shrinks instead of queueing.
        self._flush_pending = True
        try:
            asyncio.get_running_loop().call_soon(self.flush)
        except RuntimeError:  # no loop (a synchronous caller): publish at once
            self.flush()

    def flush(self) -> None:
        """Publish one Telemetry snapshot for every airframe updated since the last flush."""
        self._flush_pending = False
        dirty, self._dirty = self._dirty, {}
        if dirty:
            now = self._clock()  # one time for the snapshots made together
            for airframe in dirty.values():
                self._publish(airframe.state.snapshot(now))

    def _rejected(self, label: str, reason: str, detail: str, count: int = 1) -> None:
        self._inst.link_rejected.labels(label, reason).inc(count)
        if self._reject_log.allow((label, reason)):
            log.warning("frame_rejected", link=label, reason=reason, detail=detail)

    def check_links(self, now_mono: float | None = None) -> None:
        """Re-evaluate link health (timeouts, failover, failback); call periodically."""
        now_mono = time.monotonic() if now_mono is None else now_mono
        for airframe in self._by_sysid.values():
            airframe.health.check(now_mono)

    def active_link(self, airframe: str) -> str | None:
        """The label of the link commands to ``airframe`` should go out on."""
        return self._by_id[airframe].health.active

    @property
    def sessions(self) -> dict[str, AirframeSession]:
        """Every airframe's session, by airframe id."""
        return self._by_id

    def peer_for(self, airframe: str, label: str) -> object | None:
        """The peer on link ``label`` that last sent an authenticated frame of ``airframe``."""
        return self._by_id[airframe].peer(label)

    def is_configured(self, airframe: str, label: str) -> bool:
        """True if link ``label`` is one of ``airframe``'s configured links."""
        known = self._by_id.get(airframe)
        return known is not None and label in known.labels

    def status(self) -> list[dict[str, object]]:
        """Per airframe: its links with health, for /status."""
        return [
            {
                "airframe": a.config.id,
                "sysid": a.config.sysid,
                "active_link": a.health.active,
                "links": a.health.status(),
                "signing": None if a.verifier is None else asdict(a.verifier.counters),
                **a.command_status(),
            }
            for a in self._by_sysid.values()
        ]

    @property
    def unknown_sysids(self) -> frozenset[int]:
        """System ids heard that no configured airframe has."""
        return frozenset(self._unknown_sysids)
