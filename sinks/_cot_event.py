"""Gateway events to Cursor-on-Target events: uids, types, times, point and detail.

One ``CotEvent`` is built once per gateway event and encoded per destination (XML, or TAK
protocol protobuf) by ``sinks._cot_codec``. No position, no event: telemetry without a fix is
skipped, never sent at 0,0. ``hae`` is height above the ellipsoid: from GPS_RAW_INT's
``alt_ellipsoid`` when the airframe sent it, else MSL plus the geoid undulation when a geoid
grid is configured, else CoT's "unknown" (9999999.0), never MSL.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Literal
from xml.sax.saxutils import escape, quoteattr

from gateway.cot_validate import UNKNOWN
from gateway.domain.sidc import Hostility, symbol_codes
from gateway.domain.targeting import CEP50_FACTOR
from gateway.events import Detection, Event, Telemetry, Track

__all__ = ["UNKNOWN", "CotEvent", "CotOptions", "build"]

# MAV_TYPE values of rotary-wing vehicles: drawn as rotary-wing UAVs (2525C A-M-H-Q).
_ROTARY = frozenset({2, 3, 4, 13, 14, 15, 29, 35})


@dataclass(frozen=True)
class CotOptions:
    """How events become CoT: uids, stale times, symbology choices."""

    uid_prefix: str = "fischer-"
    callsign_prefix: str = "FISCHER "
    stale_s: dict[str, float] = field(
        default_factory=lambda: {"telemetry": 15.0, "detection": 120.0, "track": 300.0}
    )
    loitering_munition: Literal["uav_attack", "missile"] = "uav_attack"
    geoid: Callable[[float, float], float | None] | None = None
    version: str = "0.1.0"


@dataclass(frozen=True)
class CotEvent:
    """A CoT 2.0 event, transport-neutral. ``xml_detail`` holds detail children as XML."""

    uid: str
    type: str
    how: str
    time: datetime
    start: datetime
    stale: datetime
    lat: float
    lon: float
    hae: float = UNKNOWN
    ce: float = UNKNOWN
    le: float = UNKNOWN
    callsign: str | None = None
    endpoint: str | None = None
    course_deg: float | None = None
    speed_mps: float | None = None
    battery_pct: int | None = None
    geopointsrc: str | None = None
    altsrc: str | None = None
    takv: tuple[str, str, str, str] | None = None  # device, platform, os, version
    xml_detail: str = ""


def _num(value: float | None) -> float:
    return UNKNOWN if value is None or not math.isfinite(value) else value


def _attrs(**values: object) -> str:
    return "".join(f" {k}={quoteattr(str(v))}" for k, v in values.items() if v is not None)


def _own_type(mav_type: int | None) -> str:
    return "a-f-A-M-H-Q" if mav_type in _ROTARY else "a-f-A-M-F-Q"


def _telemetry(event: Telemetry, opts: CotOptions) -> CotEvent | None:
    pos = event.position
    if pos is None:
        return None
    hae, altsrc = pos.alt_hae_m, "GPS"
    if hae is None and pos.alt_msl_m is not None and opts.geoid is not None:
        undulation = opts.geoid(pos.lat_deg, pos.lon_deg)
        if undulation is not None:
            hae, altsrc = pos.alt_msl_m + undulation, "CALC"
    callsign = opts.callsign_prefix + event.airframe
    remarks = [f"link {event.active_link or '-'}"]
    if event.ew_mode:
        remarks.append(f"EW {event.ew_mode}")
    if event.alt_agl_m is not None:
        remarks.append(f"AGL {event.alt_agl_m:.0f} m")
    if event.endurance_remaining_min is not None:
        remarks.append(f"endurance {event.endurance_remaining_min:.0f} min")
    detail = (
        f"<uid{_attrs(Droid=callsign)}/>"
        f'<__group name="Cyan" role="Team Member"/>'
        f"<remarks>{escape(', '.join(remarks))}</remarks>"
    )
    return CotEvent(
        uid=opts.uid_prefix + event.airframe,
        type=_own_type(event.mav_type),
        how="m-g",
        time=event.time,
        start=event.time,
        stale=event.time + timedelta(seconds=opts.stale_s["telemetry"]),
        lat=pos.lat_deg,
        lon=pos.lon_deg,
        hae=_num(hae),
        ce=_num(event.h_acc_m),
        callsign=callsign,
        endpoint="*:-1:stcp",
        course_deg=None if event.heading_deg is None else event.heading_deg % 360.0,
        speed_mps=event.groundspeed_mps,
        battery_pct=None if event.battery_pct is None else round(event.battery_pct),
        geopointsrc="GPS",
        altsrc=altsrc if hae is not None else "???",
        takv=("Fischer 26E", "fischer-gateway", "linux", opts.version),
        xml_detail=detail,
    )


def _symbol(object_class: str, hostility: Hostility, opts: CotOptions) -> tuple[str, str, str]:
    try:
        codes = symbol_codes(object_class, hostility, loitering_munition=opts.loitering_munition)
    except KeyError:
        letter = {"hostile": "h", "suspect": "s", "friend": "f", "neutral": "n"}.get(hostility, "u")
        return f"a-{letter}-G", "", ""
    return codes.cot_type, codes.sidc_2525c, codes.sidc_2525d


def _link(uid: str, type_: str) -> str:
    return f"<link{_attrs(uid=uid, type=type_, relation='p-p')}/>"


def _detection(event: Detection, opts: CotOptions) -> CotEvent:
    type_, c, d = _symbol(event.object_class, "hostile", opts)
    remarks = (
        f"{event.sensor.value.upper()} detection: {event.object_class}"
        f"{' ' + event.subtype if event.subtype else ''}, conf {event.confidence:.2f}"
    )
    detail = (
        f"<remarks>{escape(remarks)}</remarks>"
        + _link(opts.uid_prefix + event.airframe, "a-f-A-M-F-Q")
        + (f"<__symbol{_attrs(sidc2525c=c, sidc2525d=d)}/>" if c else "")
    )
    return CotEvent(
        uid=f"{opts.uid_prefix}det-{event.event_id}",
        type=type_,
        how="m-i",
        time=event.time,
        start=event.time,
        stale=event.time + timedelta(seconds=opts.stale_s["detection"]),
        lat=event.position.lat_deg,
        lon=event.position.lon_deg,
        hae=_num(event.position.alt_hae_m),
        ce=event.sigma_h_m,
        callsign=f"D-{event.object_class.upper()}",
        xml_detail=detail,
    )


def _track(event: Track, opts: CotOptions) -> CotEvent:
    type_, c, d = _symbol(event.object_class, event.hostility, opts)
    if event.sidc:
        c = event.sidc
    remarks = (
        f"Fused track: {event.object_class}{' ' + event.subtype if event.subtype else ''}, "
        f"conf {event.confidence:.2f}, {len(event.detection_ids)} detections, "
        f"CEP50 {event.cep50_m:.0f} m, CEP90 {event.cep90_m:.0f} m"
    )
    links = "".join(_link(opts.uid_prefix + a, "a-f-A-M-F-Q") for a in event.airframes)
    course = speed = None
    if event.velocity is not None:
        north, east = event.velocity.north_mps, event.velocity.east_mps
        speed = math.hypot(north, east)
        course = math.degrees(math.atan2(east, north)) % 360.0
    return CotEvent(
        uid=f"{opts.uid_prefix}trk-{event.track_id}",
        type=type_,
        how="m-f",
        time=event.time,
        start=event.time,
        stale=event.time + timedelta(seconds=opts.stale_s["track"]),
        lat=event.position.lat_deg,
        lon=event.position.lon_deg,
        hae=_num(event.position.alt_hae_m),
        ce=event.cep50_m / CEP50_FACTOR,  # CoT's ce is 1σ
        callsign=f"T-{event.track_id} {event.object_class.upper()}",
        course_deg=course,
        speed_mps=speed,
        xml_detail=f"<remarks>{escape(remarks)}</remarks>"
        + links
        + (f"<__symbol{_attrs(sidc2525c=c, sidc2525d=d)}/>" if c else ""),
    )


def build(event: Event, opts: CotOptions) -> CotEvent | None:
    """The CoT event for a gateway event, or None if it has none (no position, other kind)."""
    if isinstance(event, Telemetry):
        return _telemetry(event, opts)
    if isinstance(event, Detection):
        return _detection(event, opts)
    if isinstance(event, Track):
        return _track(event, opts)
    return None
