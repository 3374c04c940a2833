"""From bytes on a link to events on the bus: parser per peer, sysid demux, link health.

``Ingest.on_data`` is the per-chunk hot path. It is synchronous and never raises: a chunk
that cannot be parsed is counted by reason and logged (rate-limited), a frame from an
unknown system id is counted and logged once per sysid, and everything else becomes
Telemetry (and, when a link comes up, LinkState) handed to ``publish``.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import timedelta

import structlog

from gateway.config import AirframeConfig
from gateway.errors import FrameError
from gateway.events import Event, LinkState
from gateway.instruments import Instruments
from gateway.logsetup import RateLimit
from gateway.mavlink import MavlinkParser
from gateway.normalise import NORMALISED_TYPES, AirframeState, Clock

__all__ = ["AirframeLink", "Ingest"]

log = structlog.get_logger(__name__)
_BOOT_ID = secrets.token_hex(4)


@dataclass(slots=True)
class AirframeLink:
    """How one airframe is heard on one link: sequence loss, last heard, up or down."""

    label: str
    priority: int
    timeout_s: float
    received: int = 0
    lost: int = 0
    last_heard_mono: float | None = None
    is_up: bool = False
    is_active: bool = False
    published: tuple[bool, bool] | None = None
    last_seq: dict[int, int] = field(default_factory=dict)

    @property
    def loss_pct(self) -> float:
        """Frames lost to sequence gaps, as a percentage of frames expected."""
        expected = self.received + self.lost
        return 100.0 * self.lost / expected if expected else 0.0


@dataclass(slots=True)
class _Airframe:
    config: AirframeConfig
    state: AirframeState
    links: dict[str, AirframeLink]


class Ingest:
    """Parses link bytes, demultiplexes by sysid and keeps per-airframe link health."""

    def __init__(
        self,
        airframes: Iterable[AirframeConfig],
        publish: Callable[[Event], None],
        instruments: Instruments,
        clock: Clock,
    ) -> None:
        self._publish = publish
        self._inst = instruments
        self._clock = clock
        self._by_sysid: dict[int, _Airframe] = {}
        for cfg in airframes:
            links = {
                link.label: AirframeLink(link.label, link.priority, cfg.link_timeout_s)
                for link in cfg.links
            }
            self._by_sysid[cfg.sysid] = _Airframe(cfg, AirframeState(cfg.id, clock), links)
        self._parsers: dict[tuple[str, object], MavlinkParser] = {}
        self._max_chunk: dict[str, int] = {}
        self._unknown_sysids: set[int] = set()
        self._reject_log = RateLimit(interval_s=10.0)
        self._link_seq = 0

    def register_link(self, label: str, max_chunk_bytes: int) -> None:
        """Declare a link endpoint before it delivers data (sets its chunk bound)."""
        self._max_chunk[label] = max_chunk_bytes

    def forget_peer(self, label: str, peer: object) -> None:
        """Drop the parser of a closed stream connection."""
        self._parsers.pop((label, peer), None)

    def on_data(self, label: str, peer: object, data: bytes) -> None:
        """Take one datagram or stream read from link ``label``; never raises."""
        inst = self._inst
        inst.link_bytes.labels(label).inc(len(data))
        inst.link_chunks.labels(label).inc()
        parser = self._parsers.get((label, peer))
        if parser is None:
            parser = MavlinkParser(max_chunk_bytes=self._max_chunk.get(label, 2048))
            self._parsers[(label, peer)] = parser
        bad_before = parser.bad
        try:
            messages = parser.feed(data)
        except FrameError as exc:
            self._rejected(label, exc.reason, str(exc))
            return
        if parser.bad != bad_before:
            self._rejected(label, "malformed", "bad MAVLink frame or CRC", parser.bad - bad_before)
        if not messages:
            return
        now_mono = time.monotonic()
        frames = inst.link_frames.labels(label)
        for msg in messages:
            frames.inc()
            sysid = msg.get_srcSystem()
            airframe = self._by_sysid.get(sysid)
            if airframe is None:
                self._unknown_sysid(label, sysid)
                continue
            self._heard(airframe, label, msg.get_srcComponent(), msg.get_seq(), now_mono)
            name = msg.get_type()
            if name in NORMALISED_TYPES:
                event = airframe.state.apply(name, msg)
                if event is not None:
                    self._publish(event)

    def _rejected(self, label: str, reason: str, detail: str, count: int = 1) -> None:
        self._inst.link_rejected.labels(label, reason).inc(count)
        if self._reject_log.allow((label, reason)):
            log.warning("frame_rejected", link=label, reason=reason, detail=detail)

    def _unknown_sysid(self, label: str, sysid: int) -> None:
        self._inst.link_ignored.labels(label, "unknown_sysid").inc()
        if sysid not in self._unknown_sysids:
            self._unknown_sysids.add(sysid)
            log.info("unknown_sysid_heard", link=label, sysid=sysid)

    def _heard(
        self, airframe: _Airframe, label: str, compid: int, seq: int, now_mono: float
    ) -> None:
        link = airframe.links.get(label)
        if link is None:
            # A shared socket can carry an airframe on a link not listed for it: track it too.
            link = AirframeLink(label, 100, airframe.config.link_timeout_s)
            airframe.links[label] = link
            log.info("airframe_heard_on_unlisted_link", airframe=airframe.config.id, link=label)
        last = link.last_seq.get(compid)
        if last is not None:
            gap = (seq - last - 1) & 0xFF
            # A gap of 255 is the same frame again (or one very late): not loss.
            if gap != 0xFF:
                link.lost += gap
        link.last_seq[compid] = seq
        link.received += 1
        link.last_heard_mono = now_mono
        if not link.is_up:
            link.is_up = True
            self._elect(airframe, f"heard on {label}")

    def check_links(self, now_mono: float | None = None) -> None:
        """Mark links not heard within their timeout as down; call periodically."""
        now_mono = time.monotonic() if now_mono is None else now_mono
        for airframe in self._by_sysid.values():
            changed = False
            for link in airframe.links.values():
                heard = link.last_heard_mono
                if link.is_up and heard is not None and now_mono - heard > link.timeout_s:
                    link.is_up = False
                    changed = True
            if changed:
                self._elect(airframe, "not heard within link_timeout_s")
            for link in airframe.links.values():
                labels = (airframe.config.id, link.label)
                self._inst.link_up.labels(*labels).set(1.0 if link.is_up else 0.0)
                self._inst.link_loss.labels(*labels).set(link.loss_pct / 100.0)
                if link.last_heard_mono is not None:
                    age = now_mono - link.last_heard_mono
                    self._inst.link_last_heard_age.labels(*labels).set(age)

    def _elect(self, airframe: _Airframe, reason: str) -> None:
        """Make the best link that is up active; publish LinkState for every link that changed."""
        up = [link for link in airframe.links.values() if link.is_up]
        best = min(up, key=lambda link: link.priority) if up else None
        airframe.state.active_link = best.label if best else None
        now = self._clock()
        now_mono = time.monotonic()
        for link in airframe.links.values():
            link.is_active = link is best
            if link.published == (link.is_up, link.is_active):
                continue
            link.published = (link.is_up, link.is_active)
            self._link_seq += 1
            last_heard = (
                None
                if link.last_heard_mono is None
                else now - timedelta(seconds=now_mono - link.last_heard_mono)
            )
            self._publish(
                LinkState(
                    event_id=f"{airframe.config.id}-link-{_BOOT_ID}-{self._link_seq}",
                    airframe=airframe.config.id,
                    time=now,
                    link=link.label,
                    is_up=link.is_up,
                    is_active=link.is_active,
                    loss_pct=min(link.loss_pct, 100.0),
                    last_heard=last_heard,
                    reason=reason,
                )
            )

    def status(self) -> list[dict[str, object]]:
        """Per airframe: its links with health, for /status."""
        now_mono = time.monotonic()
        out: list[dict[str, object]] = []
        for airframe in self._by_sysid.values():
            links = [
                {
                    "link": link.label,
                    "priority": link.priority,
                    "up": link.is_up,
                    "active": link.is_active,
                    "loss_pct": round(link.loss_pct, 3),
                    "frames": link.received,
                    "last_heard_age_s": None
                    if link.last_heard_mono is None
                    else round(now_mono - link.last_heard_mono, 3),
                }
                for link in airframe.links.values()
            ]
            out.append(
                {"airframe": airframe.config.id, "sysid": airframe.config.sysid, "links": links}
            )
        return out

    @property
    def unknown_sysids(self) -> frozenset[int]:
        """System ids heard that no configured airframe has."""
        return frozenset(self._unknown_sysids)
