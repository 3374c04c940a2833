"""Gateway events to Cursor-on-Target events: uids, types, times, point and detail.

One ``CotEvent`` is built per gateway event and then encoded per destination (XML, or TAK
protocol protobuf) by ``sinks.cot.codec``. No position, no event: telemetry without one is
skipped, and so is any position exactly at 0,0; nothing is ever sent at Null Island.

``hae`` is height above the WGS 84 ellipsoid, never MSL: the position's ``alt_hae_m`` (from
GPS_RAW_INT ``alt_ellipsoid``) when present, else ``alt_msl_m`` plus the EGM96 geoid
undulation, else CoT's "unknown" 9999999.0. ``ce`` is 1σ horizontal error in metres: the
airframe's ``h_acc_m``, a detection's ``sigma_h_m``, a track's CEP50 / 1.1774.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from xml.sax.saxutils import escape, quoteattr

from gateway.domain.sidc import Hostility
from gateway.domain.symbols import (
    LoiteringMunition,
    Symbol,
    cot_type_from_sidc,
    object_symbol,
    own_symbol,
)
from gateway.domain.targeting import CEP50_FACTOR
from gateway.events import BlueForce, Detection, Event, Position, Telemetry, Track
from sinks.cot.validate import UNKNOWN

__all__ = [
    "CotEvent",
    "CotOptions",
    "Geoid",
    "StaleTimes",
    "build",
    "how_and_source",
    "own_uid",
    "xml_attribute",
    "xml_safe",
]

Geoid = Callable[[float, float], float | None]
"""Geoid undulation N in metres at (lat, lon), or None where unknown."""

_NOT_IN_UID = re.compile(r"[\s\x00-\x1f\x7f]")
# Characters XML 1.0 cannot carry at all, escaped or not.
_NOT_IN_XML = re.compile("[^\t\n\r\x20-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")


def xml_safe(text: str) -> str:
    """``text`` without the characters XML 1.0 forbids (controls, U+FFFE/FFFF, surrogates)."""
    return _NOT_IN_XML.sub("\ufffd", text)


#: Attribute values that neither ``xml_safe`` nor ``quoteattr`` would change (most are
#: numbers, times, uids and CoT types): quoted as they are, without the two passes.
_PLAIN_ATTRIBUTE = re.compile(r"[\w .:+/#@,()-]*", re.ASCII)


def xml_attribute(text: str) -> str:
    """``text`` as a quoted XML attribute value, made XML-safe and escaped."""
    if _PLAIN_ATTRIBUTE.fullmatch(text):
        return f'"{text}"'
    return quoteattr(xml_safe(text))


@dataclass(frozen=True, slots=True)
class StaleTimes:
    """How long each kind stays valid on the receivers' maps, in seconds; every kind has one."""

    telemetry_s: float = 15.0
    detection_s: float = 120.0
    track_s: float = 300.0
    blue_force_s: float = 600.0


@dataclass(frozen=True)
class CotOptions:
    """How gateway events become CoT: uids, callsigns, stale times, symbology."""

    uid_prefix: str = "fischer-"
    callsign_prefix: str = "FISCHER "
    stale: StaleTimes = field(default_factory=StaleTimes)
    loitering_munition: LoiteringMunition = "uav_attack"
    detection_hostility: Hostility = "hostile"
    geoid: Geoid | None = None
    group: tuple[str, str] | None = None  # __group name and role for own airframes
    version: str = "0"


@dataclass(frozen=True, slots=True)
class CotEvent:
    """A CoT 2.0 event, transport-neutral.

    The detail children that TAK protobuf carries in fields of their own are kept as fields
    (contact, __group, track, status, precisionlocation, takv); every other child is already
    serialized, escaped XML in ``xml_detail``.
    """

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
    group: tuple[str, str] | None = None
    course_deg: float | None = None
    speed_mps: float | None = None
    battery_pct: int | None = None
    geopointsrc: str | None = None
    altsrc: str | None = None
    takv: tuple[str, str, str, str] | None = None  # device, platform, os, version
    xml_detail: str = ""

    def content(self) -> tuple[object, ...]:
        """Everything but the times: equal content means nothing new to show."""
        return (
            self.type, self.how, self.lat, self.lon, self.hae, self.ce, self.le, self.callsign,
            self.course_deg, self.speed_mps, self.battery_pct, self.xml_detail,
        )  # fmt: skip


def _uid(*parts: str) -> str:
    return xml_safe(_NOT_IN_UID.sub("_", "".join(parts)))


def own_uid(uid_prefix: str, airframe: str) -> str:
    """The CoT uid of our own airframe ``airframe`` (its position reports and links)."""
    return _uid(uid_prefix, airframe)


def _num(value: float | None) -> float:
    return UNKNOWN if value is None or not math.isfinite(value) else value


def _attrs(**values: object) -> str:
    return "".join(f" {k}={xml_attribute(str(v))}" for k, v in values.items() if v is not None)


def _element(tag: str, text: str | None = None, **values: object) -> str:
    if text is None:
        return f"<{tag}{_attrs(**values)}/>"
    return f"<{tag}{_attrs(**values)}>{escape(xml_safe(text))}</{tag}>"


def _has_fix(position: Position) -> bool:
    return not (position.lat_deg == 0.0 and position.lon_deg == 0.0)


def _hae(position: Position, geoid: Geoid | None) -> tuple[float, str]:
    """hae and its precisionlocation ``altsrc``."""
    if position.alt_hae_m is not None and math.isfinite(position.alt_hae_m):
        return position.alt_hae_m, "GPS"
    if position.alt_msl_m is not None and geoid is not None:
        undulation = geoid(position.lat_deg, position.lon_deg)
        if undulation is not None and math.isfinite(position.alt_msl_m):
            return position.alt_msl_m + undulation, "CALC"
    return UNKNOWN, "???"


#: GPS_RAW_INT fix types from a 3-D fix up, and the precisionlocation source each is.
_GPS_SOURCES = {3: "GPS", 4: "DGPS", 5: "RTK", 6: "RTK", 8: "GPS"}  # 8 is PPP


def how_and_source(fix_type: int | None) -> tuple[str, str | None]:
    """CoT ``how`` and ``geopointsrc`` for an own position with GPS ``fix_type``.

    ``m-g``/GPS only with a 3-D fix (cot.md section 5). With fix type 0 (no GPS), 1 (no fix)
    or 2 (2-D) the autopilot's position is its estimator's dead reckoning: ``m-p`` (predicted)
    and ``ESTIMATED``, never GPS. Fix type 7 (static) is a configured position (``m-c``,
    ``USER``). Unknown (no GPS_RAW_INT seen) is ``m-g`` with the source left unknown (``???``):
    the autopilot's navigation solution, with no claim about what fed it.
    """
    if fix_type is None:
        return "m-g", "???"
    if fix_type in _GPS_SOURCES:
        return "m-g", _GPS_SOURCES[fix_type]
    if fix_type == 7:
        return "m-c", "USER"
    return "m-p", "ESTIMATED"


def _course(north: float, east: float) -> float:
    # Rounded before the modulo so 359.999 does not print as "360.00" (course must be < 360).
    return round(math.degrees(math.atan2(east, north)), 2) % 360.0


def _symbol_detail(symbol: Symbol) -> str:
    # Our own element: CoT's type cannot carry echelon or the 2525D code (cot.md §3).
    return _element("__symbol", sidc2525c=symbol.sidc_2525c, sidc2525d=symbol.sidc_2525d)


def _telemetry(event: Telemetry, opts: CotOptions, own: Symbol) -> CotEvent | None:
    pos = event.position
    if pos is None or not _has_fix(pos):
        return None
    hae, altsrc = _hae(pos, opts.geoid)
    callsign = xml_safe(opts.callsign_prefix + event.airframe)
    course = speed = None
    if event.velocity is not None:
        north, east = event.velocity.north_mps, event.velocity.east_mps
        course, speed = _course(north, east), math.hypot(north, east)
    elif event.heading_deg is not None and event.groundspeed_mps is not None:
        course, speed = round(event.heading_deg, 2) % 360.0, event.groundspeed_mps
    how, geopointsrc = how_and_source(event.gps_fix_type)
    remarks = [f"link {event.active_link or '-'}"]
    if event.ew_mode:
        remarks.append(f"EW {event.ew_mode}")
    if event.alt_agl_m is not None:
        remarks.append(f"AGL {event.alt_agl_m:.0f} m")
    if event.endurance_remaining_min is not None:
        remarks.append(f"endurance {event.endurance_remaining_min:.0f} min")
    if event.origin_node is not None:
        remarks.append(f"from node {event.origin_node}")
    return CotEvent(
        uid=own_uid(opts.uid_prefix, event.airframe),
        type=own.cot_type,
        how=how,
        time=event.time,
        start=event.time,
        stale=event.time + timedelta(seconds=opts.stale.telemetry_s),
        lat=pos.lat_deg,
        lon=pos.lon_deg,
        hae=_num(hae),
        ce=_num(event.h_acc_m),
        callsign=callsign,
        group=opts.group,
        course_deg=course,
        speed_mps=speed,
        battery_pct=None if event.battery_pct is None else round(event.battery_pct),
        geopointsrc=geopointsrc,
        altsrc=altsrc,
        takv=("Fischer 26E", "fischer-gateway", "linux", opts.version),
        xml_detail=_element("uid", Droid=callsign)
        + _symbol_detail(own)
        + _element("remarks", ", ".join(remarks)),
    )


def _link(opts: CotOptions, airframe: str, own_types: Mapping[str, str]) -> str:
    own_type = own_types.get(airframe, own_symbol(None).cot_type)
    return _element("link", uid=own_uid(opts.uid_prefix, airframe), type=own_type, relation="p-p")


def _detection(event: Detection, opts: CotOptions, own_types: Mapping[str, str]) -> CotEvent:
    hostility = opts.detection_hostility
    symbol = object_symbol(event.object_class, hostility, opts.loitering_munition)
    hae, _ = _hae(event.position, opts.geoid)
    what = event.object_class + (f" {event.subtype}" if event.subtype else "")
    remarks = f"{event.sensor.value.upper()} detection: {what}, confidence {event.confidence:.2f}"
    if event.origin_node is not None:
        remarks += f"; from node {event.origin_node}"
    return CotEvent(
        uid=_uid(opts.uid_prefix, "det-", event.event_id),
        type=symbol.cot_type,
        how="m-i",
        time=event.time,
        start=event.time,
        stale=event.time + timedelta(seconds=opts.stale.detection_s),
        lat=event.position.lat_deg,
        lon=event.position.lon_deg,
        hae=_num(hae),
        ce=event.sigma_h_m,
        callsign=xml_safe(f"D-{event.object_class.upper()}"),
        xml_detail=_element("remarks", remarks)
        + _link(opts, event.airframe, own_types)
        + _symbol_detail(symbol),
    )


def _track(event: Track, opts: CotOptions, own_types: Mapping[str, str]) -> CotEvent:
    symbol = object_symbol(event.object_class, event.hostility, opts.loitering_munition, event.sidc)
    hae, _ = _hae(event.position, opts.geoid)
    what = event.object_class + (f" {event.subtype}" if event.subtype else "")
    remarks = (
        f"Fused track: {what}, {event.hostility}, confidence {event.confidence:.2f}, "
        f"{len(event.detection_ids)} detections, "
        f"CEP50 {event.cep50_m:.0f} m, CEP90 {event.cep90_m:.0f} m"
    )
    if event.origin_nodes:
        remarks += f"; detections from nodes {', '.join(event.origin_nodes)}"
    course = speed = None
    if event.velocity is not None:
        north, east = event.velocity.north_mps, event.velocity.east_mps
        course, speed = _course(north, east), math.hypot(north, east)
    stale = event.time + timedelta(seconds=opts.stale.track_s)
    if event.status == "merged":
        # A second track of an object another uid shows: stale at once, so the map drops it.
        remarks += f"; merged into T-{event.merged_into}"
        stale = event.time + timedelta(seconds=1)
    return CotEvent(
        uid=_uid(opts.uid_prefix, "trk-", event.track_id),
        type=symbol.cot_type,
        how="m-f",
        time=event.time,
        start=event.time,
        stale=stale,
        lat=event.position.lat_deg,
        lon=event.position.lon_deg,
        hae=_num(hae),
        ce=event.cep50_m / CEP50_FACTOR,  # CoT's ce is 1σ; CEP50 = 1.1774σ
        callsign=xml_safe(f"T-{event.track_id} {event.object_class.upper()}"),
        course_deg=course,
        speed_mps=speed,
        xml_detail=_element("remarks", remarks)
        + "".join(_link(opts, a, own_types) for a in event.airframes)
        + _symbol_detail(symbol),
    )


def _blue_force(event: BlueForce, opts: CotOptions) -> CotEvent:
    # NFFI and CoT carry friendly units only: whatever the SIDC says, the type stays friendly
    # ("a" assumed friend kept), so a relayed report can never draw a unit as hostile.
    cot_type = cot_type_from_sidc(event.sidc) if event.sidc else "a-f-G"
    if cot_type[2] not in "fa":
        cot_type = cot_type[:2] + "f" + cot_type[3:]
    hae, _ = _hae(event.position, opts.geoid)
    callsign = xml_safe(event.callsign or event.uid)
    # The callsign shown on ATAK is the relayed unit's; the remarks say how far its sender
    # was checked ("Blue force relay (NFFI, address_only)"), so nobody takes it for ours.
    detail = _element(
        "remarks", f"Blue force relay ({event.source.upper()}, {event.provenance.value})"
    )
    if event.sidc:
        affiliation = cot_type[2]
        detail = (
            _element("usericon", iconsetpath=f"COT_MAPPING_2525C/a-{affiliation}/{cot_type}")
            + detail
        )
    return CotEvent(
        uid=_uid(event.uid),
        type=cot_type,
        how="h-e",  # a relayed report: not our own measurement (cot.md §5)
        time=event.time,
        start=event.time,
        stale=event.time + timedelta(seconds=opts.stale.blue_force_s),
        lat=event.position.lat_deg,
        lon=event.position.lon_deg,
        hae=_num(hae),
        callsign=callsign,
        course_deg=None if event.course_deg is None else round(event.course_deg, 2) % 360.0,
        speed_mps=event.speed_mps,
        xml_detail=detail,
    )


def build(
    event: Event, opts: CotOptions, own_types: dict[str, str] | None = None
) -> CotEvent | None:
    """The CoT event for a gateway event; None when it has none (no position, other kind).

    ``own_types`` maps airframe → CoT type; telemetry updates it, and detections and tracks
    use it for their ``link`` to the reporting airframe.
    """
    types = own_types if own_types is not None else {}
    if isinstance(event, Telemetry):
        own = own_symbol(event.mav_type)
        types[event.airframe] = own.cot_type
        return _telemetry(event, opts, own)
    if isinstance(event, Detection):
        return None if not _has_fix(event.position) else _detection(event, opts, types)
    if isinstance(event, Track):
        return None if not _has_fix(event.position) else _track(event, opts, types)
    if isinstance(event, BlueForce):
        return None if not _has_fix(event.position) else _blue_force(event, opts)
    return None
