"""SWECCIS Functional Area Service documents: the gateway's events as XML, and back for orders.

No public SWECCIS schema exists, so the documents are ours, versioned and shipped:
``schemas/sweccis-fas.xsd`` (version 1, namespace ``urn:fischer-gateway:sweccis:fas:1``)
and ``sweccis-fas-2.xsd`` (version 2, ``...:fas:2``). Version 2 publishes a merge as what it
is: a Track with Status ``merged`` naming the survivor in ``MergedInto``; version 1 has no
such status, so there a merged track ends as ``lost``. Every encoder takes the ``version``
to write (``"1"`` by default: a receiver that validates against version 1 keeps working);
both versions are read. What goes where (docs/sweccis.md has the table and examples):

- a ``Detection`` or a ``Track`` is one **Intel** document, its id the event id;
- a ``Telemetry`` is a **Logistics** document (the airframe's health: system status, GPS fix,
  link in use, battery, endurance, EW mode), id ``<event id>/logistics``, and an
  **Operations** document (position, attitude, motion, link in use, mission status), id
  ``<event id>/operations``, only when the airframe has a position (never 0,0 for unknown);
- the server sends **Orders** documents (a five-line order), read into ``FiveLineOrder``
  by ``sinks.sweccis.order``;
- an ``OrderStatus`` (the orders processor's answer to an order) is an **OrderStatus**
  document of the Orders FAS, gateway to server, its id the status event's id;
- the transport's control documents: ``Register`` (ours), ``Registered`` and ``Ack`` (both
  ways: the server acknowledges our documents, we acknowledge its orders).

Encoding refuses, with ``ValueError`` naming the event and the field, any value the schema
cannot hold (a NaN, an id with spaces, a class name over 64 characters): the caller decides
what becomes of that event. ``parse_document`` reads what a server sends, within a byte
bound, and raises ``DocumentError`` naming the element for anything else.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal, cast

from gateway.events import (
    Detection,
    Event,
    FiveLineOrder,
    OrderStatus,
    Position,
    Telemetry,
    Track,
)
from sinks.sweccis.fasxml import (
    MAX_DOCUMENT_BYTES,
    NAMESPACE,
    SCHEMA_VERSION,
    SCHEMA_VERSIONS,
    DocumentError,
    Fas,
    Node,
    add,
    check_id,
    check_text,
    clean_text,
    load_schema,
    number,
    parse_root,
    time_text,
    to_bytes,
)
from sinks.sweccis.order import decode_order

__all__ = [
    "MAX_DOCUMENT_BYTES",
    "NAMESPACE",
    "SCHEMA_VERSION",
    "SCHEMA_VERSIONS",
    "Ack",
    "AckStatus",
    "Document",
    "DocumentError",
    "Fas",
    "OrderDocument",
    "Registered",
    "encode_ack",
    "encode_event",
    "encode_order_status",
    "encode_register",
    "load_schema",
    "parse_document",
]

AckStatus = Literal["accepted", "duplicate", "rejected"]
_ACK_STATUSES: frozenset[str] = frozenset({"accepted", "duplicate", "rejected"})
_ALT = (-100_000.0, 1_000_000.0)
_MAX = 1.7976931348623157e308
# MAVLink MAV_STATE and GPS_FIX_TYPE by value; a value beyond the table is "unknown".
_SYSTEM_STATUS = (
    "uninit", "boot", "calibrating", "standby", "active", "critical", "emergency", "poweroff",
    "flight_termination",
)  # fmt: skip
_GPS_FIX = (
    "no_gps", "no_fix", "fix_2d", "fix_3d", "dgps", "rtk_float", "rtk_fixed", "static", "ppp",
)  # fmt: skip
# ArduPlane's custom modes, named only for an ArduPilot (autopilot 3) fixed wing (type 1).
_ARDUPLANE_MODES = {
    0: "MANUAL", 1: "CIRCLE", 2: "STABILIZE", 3: "TRAINING", 4: "ACRO", 5: "FBWA", 6: "FBWB",
    7: "CRUISE", 8: "AUTOTUNE", 10: "AUTO", 11: "RTL", 12: "LOITER", 13: "TAKEOFF",
    14: "AVOID_ADSB", 15: "GUIDED", 17: "QSTABILIZE", 18: "QHOVER", 19: "QLOITER", 20: "QLAND",
    21: "QRTL", 22: "QAUTOTUNE", 23: "QACRO", 24: "THERMAL", 25: "LOITER_ALT_QLAND",
}  # fmt: skip
_EW_MODES = frozenset({"permissive", "active", "heavy"})


@dataclass(frozen=True, slots=True)
class Document:
    """One document to publish: its FAS, its id (what the ack names) and its event."""

    fas: Fas
    doc_id: str
    event_id: str
    payload: bytes


@dataclass(frozen=True, slots=True)
class Registered:
    """The server's answer to our ``Register`` ``ref``: the FAS it registered."""

    ref: str
    publish: frozenset[Fas]
    subscribe: frozenset[Fas]


@dataclass(frozen=True, slots=True)
class Ack:
    """The answer to one document: accepted, duplicate (both delivered) or rejected."""

    ref: str
    status: AckStatus
    reason: str | None = None


@dataclass(frozen=True, slots=True)
class OrderDocument:
    """An ``Orders`` document: its id (to acknowledge) and the order it carries."""

    doc_id: str
    order: FiveLineOrder


# -- events to documents -----------------------------------------------------------------------


def _opt(value: float | None, field: str, low: float = -_MAX, high: float = _MAX) -> str | None:
    return None if value is None else number(value, field, low, high)


def _position(parent: ET.Element, tag: str, position: Position, **extra: str | None) -> None:
    add(
        parent,
        tag,
        latDeg=number(position.lat_deg, f"{tag}/latDeg", -90.0, 90.0),
        lonDeg=number(position.lon_deg, f"{tag}/lonDeg", -180.0, 180.0),
        altMslM=_opt(position.alt_msl_m, f"{tag}/altMslM", *_ALT),
        altHaeM=_opt(position.alt_hae_m, f"{tag}/altHaeM", *_ALT),
        **extra,
    )


def _root(fas: Fas, doc_id: str, version: str = SCHEMA_VERSION) -> ET.Element:
    return ET.Element(fas.value, {"version": _version(version), "id": check_id(doc_id, "@id")})


def _version(version: str) -> str:
    if version not in SCHEMA_VERSIONS:
        raise ValueError(f"SWECCIS FAS version {version!r} is not one of {sorted(SCHEMA_VERSIONS)}")
    return version


def _late(parent: ET.Element, late_by_s: float | None) -> None:
    if late_by_s is not None:
        add(parent, "LateByS", number(late_by_s, "LateByS", 0.0))


def _detection(detection: Detection, version: str) -> bytes:
    root = _root(Fas.INTEL, detection.event_id, version)
    body = add(root, "Detection")
    add(body, "Time", time_text(detection.time))
    add(body, "Airframe", check_text(detection.airframe, "Airframe", 128, min_length=1))
    add(body, "Sensor", detection.sensor.value)
    add(body, "Class", check_text(detection.object_class, "Class", 64))
    if detection.subtype:
        add(body, "Subtype", check_text(detection.subtype, "Subtype", 64))
    add(body, "Confidence", number(detection.confidence, "Confidence", 0.0, 1.0))
    _position(body, "Position", detection.position)
    add(body, "Uncertainty", sigmaHM=number(detection.sigma_h_m, "Uncertainty/sigmaHM", 0.0))
    _late(body, detection.late_by_s)
    return to_bytes(root)


def _names(parent: ET.Element, tag: str, item: str, values: Iterable[str], limit: int) -> None:
    unique = list(dict.fromkeys(values))  # a sensor or airframe named twice is one
    if not unique:
        return
    if len(unique) > limit:
        raise ValueError(f"{tag}: {len(unique)} entries, more than {limit}")
    holder = add(parent, tag)
    for value in unique:
        add(holder, item, check_text(value, f"{tag}/{item}", 128, min_length=1))


def _track(track: Track, version: str) -> bytes:
    root = _root(Fas.INTEL, track.event_id, version)
    body = add(root, "Track")
    add(body, "TrackId", check_text(track.track_id, "TrackId", 128, min_length=1))
    if track.status == "merged" and version == "1":
        # Version 1 knows created/updated/lost: a merged track's id ends here as lost (its
        # object lives on under the survivor's id, which version 1 cannot name).
        add(body, "Status", "lost")
    elif track.status == "merged":
        if track.merged_into is None:
            raise ValueError("MergedInto: a merged track must name the track it merged into")
        add(body, "Status", "merged")
        add(body, "MergedInto", check_text(track.merged_into, "MergedInto", 128, min_length=1))
    else:
        add(body, "Status", track.status)
    add(body, "Time", time_text(track.time))
    add(body, "FirstSeen", time_text(track.first_seen))
    add(body, "LastSeen", time_text(track.last_seen))
    add(body, "Class", check_text(track.object_class, "Class", 64))
    if track.subtype:
        add(body, "Subtype", check_text(track.subtype, "Subtype", 64))
    add(body, "Hostility", track.hostility)
    if track.sidc:
        add(body, "Sidc", check_text(track.sidc, "Sidc", 64))
    add(body, "Confidence", number(track.confidence, "Confidence", 0.0, 1.0))
    add(body, "ClassConflict", number(track.class_conflict, "ClassConflict", 0.0, 1.0))
    _position(body, "Position", track.position)
    add(
        body,
        "Uncertainty",
        cep50M=number(track.cep50_m, "Uncertainty/cep50M", 0.0),
        cep90M=number(track.cep90_m, "Uncertainty/cep90M", 0.0),
    )
    if track.speed_mps is not None or track.course_deg is not None:
        add(
            body,
            "Kinematics",
            speedMps=_opt(track.speed_mps, "Kinematics/speedMps", 0.0),
            courseDeg=_opt(track.course_deg, "Kinematics/courseDeg", 0.0, math.nextafter(360, 0)),
        )
    _names(body, "Sensors", "Sensor", (s.value for s in track.sensors), 3)
    _names(body, "Airframes", "Airframe", track.airframes, 64)
    add(body, "DetectionCount", str(track.detection_count))
    _late(body, track.late_by_s)
    return to_bytes(root)


def _name_of(table: tuple[str, ...], value: int) -> str:
    return table[value] if 0 <= value < len(table) else "unknown"


def _logistics(telemetry: Telemetry, version: str) -> bytes:
    t = telemetry
    root = _root(Fas.LOGISTICS, f"{t.event_id}/logistics", version)
    body = add(root, "AirframeHealth")
    add(body, "Airframe", check_text(t.airframe, "Airframe", 128, min_length=1))
    add(body, "Time", time_text(t.time))
    if t.system_status is not None:
        add(body, "SystemStatus", _name_of(_SYSTEM_STATUS, t.system_status))
    if t.gps_fix_type is not None or t.satellites_visible is not None or t.h_acc_m is not None:
        satellites = t.satellites_visible
        if satellites is not None and not 0 <= satellites <= 255:
            raise ValueError(f"Gps/satellites: {satellites} is outside 0..255")
        add(
            body,
            "Gps",
            fix=None if t.gps_fix_type is None else _name_of(_GPS_FIX, t.gps_fix_type),
            satellites=None if satellites is None else str(satellites),
            hAccM=_opt(t.h_acc_m, "Gps/hAccM", 0.0),
        )
    if t.active_link:
        add(body, "LinkInUse", check_text(t.active_link, "LinkInUse", 128))
    battery = {
        "pct": _opt(t.battery_pct, "Battery/pct", 0.0, 100.0),
        "voltageV": _opt(t.battery_voltage_v, "Battery/voltageV"),
        "currentA": _opt(t.battery_current_a, "Battery/currentA"),
        "consumedWh": _opt(t.battery_consumed_wh, "Battery/consumedWh"),
        "timeRemainingS": _opt(t.battery_time_remaining_s, "Battery/timeRemainingS", 0.0),
    }
    if any(value is not None for value in battery.values()):
        add(body, "Battery", **battery)
    if t.endurance_remaining_min is not None:
        add(
            body,
            "EnduranceRemainingMin",
            number(t.endurance_remaining_min, "EnduranceRemainingMin", 0.0),
        )
    if t.ew_mode is not None:
        if t.ew_mode not in _EW_MODES:
            raise ValueError(f"EwMode: {t.ew_mode[:40]!r} is not one of {sorted(_EW_MODES)}")
        add(body, "EwMode", t.ew_mode)
    return to_bytes(root)


def _mission(telemetry: Telemetry) -> dict[str, str | None]:
    t = telemetry
    mode = None
    if t.custom_mode is not None and t.autopilot == 3 and t.mav_type == 1:
        mode = _ARDUPLANE_MODES.get(t.custom_mode)
    if t.custom_mode is not None and not 0 <= t.custom_mode < 2**32:
        raise ValueError(f"Mission/customMode: {t.custom_mode} is outside 0..4294967295")
    return {
        "armed": None if t.is_armed is None else ("true" if t.is_armed else "false"),
        "mode": mode,
        "customMode": None if t.custom_mode is None else str(t.custom_mode),
        "systemStatus": None
        if t.system_status is None
        else _name_of(_SYSTEM_STATUS, t.system_status),
    }


def _operations(telemetry: Telemetry, version: str) -> bytes | None:
    t = telemetry
    if t.position is None:
        return None  # no position, no Operations document
    root = _root(Fas.OPERATIONS, f"{t.event_id}/operations", version)
    body = add(root, "AirframeState")
    add(body, "Airframe", check_text(t.airframe, "Airframe", 128, min_length=1))
    add(body, "Time", time_text(t.time))
    _position(
        body,
        "Position",
        t.position,
        altRelHomeM=_opt(t.position.alt_rel_home_m, "Position/altRelHomeM", *_ALT),
        altAglM=_opt(t.alt_agl_m, "Position/altAglM", *_ALT),
    )
    if t.attitude is not None:
        a = t.attitude
        add(
            body,
            "Attitude",
            rollDeg=number(math.degrees(a.roll_rad), "Attitude/rollDeg"),
            pitchDeg=number(math.degrees(a.pitch_rad), "Attitude/pitchDeg"),
            yawDeg=number(math.degrees(a.yaw_rad), "Attitude/yawDeg"),
        )
    v = t.velocity
    motion = {
        "groundspeedMps": _opt(t.groundspeed_mps, "Motion/groundspeedMps"),
        "airspeedMps": _opt(t.airspeed_mps, "Motion/airspeedMps"),
        "climbMps": _opt(t.climb_mps, "Motion/climbMps"),
        "headingDeg": _opt(t.heading_deg, "Motion/headingDeg"),
        "northMps": None if v is None else number(v.north_mps, "Motion/northMps"),
        "eastMps": None if v is None else number(v.east_mps, "Motion/eastMps"),
        "downMps": None if v is None else number(v.down_mps, "Motion/downMps"),
    }
    if any(value is not None for value in motion.values()):
        add(body, "Motion", **motion)
    if t.active_link:
        add(body, "LinkInUse", check_text(t.active_link, "LinkInUse", 128))
    mission = _mission(t)
    if any(value is not None for value in mission.values()):
        add(body, "Mission", **mission)
    return to_bytes(root)


def encode_event(
    event: Event,
    *,
    logistics: bool = True,
    operations: bool = True,
    version: str = SCHEMA_VERSION,
) -> list[Document]:
    """The documents of one event in FAS ``version``, in the order they are sent (none for
    a skipped FAS).

    A detection or track is one Intel document; telemetry is a Logistics document (unless
    ``logistics`` is False) and an Operations document (unless ``operations`` is False or
    the airframe has no position). Raises ``ValueError`` naming the event and the field
    for a value the schema cannot hold, and for an event kind no FAS carries.
    """
    try:
        if isinstance(event, Detection):
            payload = _detection(event, version)
            return [Document(Fas.INTEL, event.event_id, event.event_id, payload)]
        if isinstance(event, Track):
            return [Document(Fas.INTEL, event.event_id, event.event_id, _track(event, version))]
        if isinstance(event, Telemetry):
            documents = []
            if logistics:
                payload = _logistics(event, version)
                doc_id = f"{event.event_id}/logistics"
                documents.append(Document(Fas.LOGISTICS, doc_id, event.event_id, payload))
            state = _operations(event, version) if operations else None
            if state is not None:
                doc_id = f"{event.event_id}/operations"
                documents.append(Document(Fas.OPERATIONS, doc_id, event.event_id, state))
            return documents
    except ValueError as exc:
        raise ValueError(f"{event.kind} {event.event_id[:80]}: cannot encode: {exc}") from None
    raise ValueError(f"{event.kind} {event.event_id[:80]}: no SWECCIS FAS carries this kind")


# -- control documents -------------------------------------------------------------------------


def encode_register(
    doc_id: str,
    client: str,
    *,
    publish: Iterable[Fas] = (),
    subscribe: Iterable[Fas] = (),
    version: str = SCHEMA_VERSION,
) -> bytes:
    """Our ``Register``, in FAS ``version``: the FAS this connection publishes and those it
    wants to receive."""
    root = ET.Element("Register", {"version": _version(version), "id": check_id(doc_id, "@id")})
    add(root, "Client", check_text(client, "Client", 128, min_length=1))
    for fas in publish:
        add(root, "Publish", fas.value)
    for fas in subscribe:
        add(root, "Subscribe", fas.value)
    return to_bytes(root)


def encode_ack(
    ref: str, status: AckStatus, reason: str | None = None, *, version: str = SCHEMA_VERSION
) -> bytes:
    """Our answer to document ``ref`` (an order); a reason is cut to 512 characters and
    anything XML cannot carry in it replaced, so only an invalid ``ref`` (or ``version``)
    raises ``ValueError``."""
    root = ET.Element(
        "Ack", {"version": _version(version), "ref": check_id(ref, "@ref"), "status": status}
    )
    if reason is not None:
        add(root, "Reason", clean_text(reason, 512))
    return to_bytes(root)


def encode_order_status(status: OrderStatus, *, version: str = SCHEMA_VERSION) -> bytes:
    """The ``OrderStatus`` document of one status in FAS ``version``; ``ValueError`` naming
    the field for a value the schema cannot hold (the reason is cleaned and cut, never
    refused)."""
    root = ET.Element(
        "OrderStatus", {"version": _version(version), "id": check_id(status.event_id, "@id")}
    )
    add(root, "OrderId", check_text(status.order_id, "OrderId", 128, min_length=1))
    add(root, "Status", status.status.value)
    add(root, "Time", time_text(status.time))
    if status.airframe:
        add(root, "Airframe", check_text(status.airframe, "Airframe", 128, min_length=1))
    if status.check:
        add(root, "Check", check_text(status.check, "Check", 128, min_length=1))
    if status.reason is not None:
        add(root, "Reason", clean_text(status.reason, 512))
    if status.mission_items is not None:
        add(root, "MissionItems", str(status.mission_items))
    return to_bytes(root)


def _fas_list(nodes: list[Node]) -> frozenset[Fas]:
    found = set()
    for node in nodes:
        text = node.text(max_length=16)
        try:
            found.add(Fas(text))
        except ValueError:
            raise node.fail(f"{text!r} is not a FAS ({', '.join(f.value for f in Fas)})") from None
    return frozenset(found)


def _ref(node: Node, name: str) -> str:
    value = node.required(name)
    try:
        return check_id(value, name)
    except ValueError as exc:
        raise node.fail(str(exc), name) from None


def parse_document(
    data: bytes, *, source: str, max_bytes: int = MAX_DOCUMENT_BYTES
) -> Registered | Ack | OrderDocument:
    """Read one document a server sent: ``Registered``, ``Ack`` or an order.

    ``source`` is the name orders are published under. Raises ``DocumentError`` naming the
    element for anything else; for an order, the error carries the document's ``doc_id``
    when it could be read, so the order can be acknowledged as rejected.
    """
    root, name = parse_root(data, max_bytes)
    node = Node(root, name)
    if name == "Registered":
        node.check_attributes(frozenset({"version", "ref"}))
        ref = _ref(node, "ref")
        kids = node.children({"Publish": 4, "Subscribe": 4})
        return Registered(
            ref, _fas_list(kids.get("Publish", [])), _fas_list(kids.get("Subscribe", []))
        )
    if name == "Ack":
        node.check_attributes(frozenset({"version", "ref", "status"}))
        ref = _ref(node, "ref")
        status = node.required("status")
        if status not in _ACK_STATUSES:
            raise node.fail(f"{status!r} is not one of {sorted(_ACK_STATUSES)}", "status")
        reasons = node.children({"Reason": 1}).get("Reason", [])
        reason = reasons[0].text(max_length=512) if reasons else None
        return Ack(ref, cast("AckStatus", status), reason)
    if name == Fas.ORDERS:
        node.check_attributes(frozenset({"version", "id"}))
        node.doc_id = _ref(node, "id")
        return OrderDocument(node.doc_id, decode_order(node, source=source))
    raise DocumentError(name, f"a server does not send <{name}> to a client")
