"""JC3IEDM object item reports: one Detection or Track as the JSON document SLB takes.

A report names the JC3IEDM entities it asserts (MIP 3.x physical column names, code values
from the C4Net enumerations; see ``docs/slb.md`` and the digest in the project's specs):
REPORTING-DATA (with its absolute timing), OBJECT-ITEM and its MATERIEL or ORGANISATION
subtype, OBJECT-TYPE with the one subtype chain that classifies it (WEAPON-TYPE TANK,
VEHICLE-TYPE ARMORD, AIRCRAFT-TYPE unmanned, UNIT-TYPE infantry platoon), the
OBJECT-ITEM-HOSTILITY-STATUS, the LOCATION as a GEOGRAPHIC-POINT and the
OBJECT-ITEM-LOCATION that places the item there with its accuracy. ``fischer`` carries what
JC3IEDM has no column for (the source event's kind, class, airframes, sensors, track state).

Identifiers are strings, stable per object: ``fg:track:<track_id>`` for every report of one
fused track, ``fg:detection:<event_id>`` for a single detection. JC3IEDM's own identifiers are
numbers allotted by the receiving database; SLB maps ours to its own.

Every document is a pure function of its event (no clock), so a retry of the same event
sends the same bytes under the same ``Idempotency-Key``. The schema ships as package data
(``sinks/slb/schemas/slb-object-item.schema.json``, JSON Schema draft 2020-12);
``SCHEMA_ID`` versions the document. The mapping tables are the ``CLASSES``, ``HOSTILITY``,
``ACCURACY`` and ``CREDIBILITY`` constants below, and nowhere else.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib.resources import files
from typing import Any

from gateway.events import Detection, Position, Track

__all__ = [
    "ACCURACY",
    "CEP50_PER_SIGMA",
    "CEP90_PER_SIGMA",
    "CLASSES",
    "CREDIBILITY",
    "HOSTILITY",
    "NAME_MAX_CHARS",
    "REPORTER_PREFIX",
    "SCHEMA_ID",
    "UNKNOWN_CLASS",
    "ClassCodes",
    "encode_object_item",
    "jc3iedm_time",
    "load_schema",
    "object_item_payload",
    "reporting_unit",
]

#: The ``schema`` member of every document; its last part is the version.
SCHEMA_ID = "fischer-gateway/slb-object-item/1"
_SCHEMA_RESOURCE = "schemas/slb-object-item.schema.json"

#: CEP50 of a circular normal error with per-axis σ: σ·√(2 ln 2).
CEP50_PER_SIGMA = 1.1774
#: The radius holding 90 % of it: σ·√(2 ln 10).
CEP90_PER_SIGMA = 2.1460
#: JC3IEDM's ``name_txt`` columns hold at most this many characters; longer names are cut.
NAME_MAX_CHARS = 100
#: The longest event id (and so ``Idempotency-Key``) a document carries.
_ID_MAX_CHARS = 256
#: The reporting unit of an airframe's reports is this prefix, a dash and the airframe id.
REPORTER_PREFIX = "Fischer26E"
#: Airframes and sensors listed in ``fischer`` at most (a track keeps its newest ones).
_LIST_MAX = 32
_TEXT_MAX = 64


@dataclass(frozen=True, slots=True)
class ClassCodes:
    """How one object class is written in JC3IEDM.

    ``item_cat_code`` is the OBJECT-ITEM and OBJECT-TYPE category (MA materiel, OR
    organisation, NKN not known). A materiel class names its EQUIPMENT-TYPE category and one
    of WEAPON-TYPE, VEHICLE-TYPE or AIRCRAFT-TYPE (always unmanned and military here); an
    organisation names its UNIT-TYPE (category, arm, echelon size). ``detection_hostility`` is
    the hostility a *single* detection of the class is reported with: the weaker "assumed"
    or "suspect" codes, since one sensor's look is not a fused, corroborated track.
    """

    item_cat_code: str
    equipment_type: str | None = None
    weapon_type: str | None = None
    vehicle_type: str | None = None
    aircraft_type: str | None = None
    unit_type: tuple[str, str, str] | None = None
    detection_hostility: str = "UNK"


#: Object class → JC3IEDM codes. A class not listed is written as ``UNKNOWN_CLASS``.
CLASSES: dict[str, ClassCodes] = {
    "tank": ClassCodes("MA", "WEPTYP", weapon_type="TANK", detection_hostility="AHO"),
    "armour": ClassCodes("MA", "VEHCLE", vehicle_type="ARMORD", detection_hostility="AHO"),
    # A Lancet, Shahed or Switchblade flies on fixed wings; a "uav" may be a multicopter.
    "loitering_munition": ClassCodes(
        "MA", "AIRCFT", aircraft_type="FIXWNG", detection_hostility="AHO"
    ),
    "uav": ClassCodes("MA", "AIRCFT", aircraft_type="NKN", detection_hostility="SUSPCT"),
    "infantry_platoon": ClassCodes(
        "OR", unit_type=("COMBAT", "INF", "PLT"), detection_hostility="SUSPCT"
    ),
}
UNKNOWN_CLASS = ClassCodes("NKN")

#: ``Track.hostility`` → OBJECT-ITEM-HOSTILITY-STATUS ``code``.
HOSTILITY: dict[str, str] = {
    "hostile": "HO",
    "suspect": "SUSPCT",
    "unknown": "UNK",
    "neutral": "NEUTRL",
    "friend": "FR",
}

#: Confidence (at least) → REPORTING-DATA ``acc_code``: 2 probable, 3 possible, 4 doubtful,
#: 5 improbable. 1 (confirmed) only for a track that several airframes or sensors agree on.
ACCURACY: tuple[tuple[float, str], ...] = ((0.9, "2"), (0.6, "3"), (0.3, "4"), (0.0, "5"))
#: Confidence (at least) → ``credibility_code``: reported as fact, plausible, uncertain.
CREDIBILITY: tuple[tuple[float, str], ...] = ((0.9, "RPTFCT"), (0.5, "RPTPLA"), (0.0, "RPTUNC"))


def load_schema() -> dict[str, Any]:
    """The object item document's JSON Schema (draft 2020-12), read from package data."""
    text = files("sinks.slb").joinpath(_SCHEMA_RESOURCE).read_text(encoding="utf-8")
    schema: dict[str, Any] = json.loads(text)
    return schema


def jc3iedm_time(value: datetime) -> str:
    """MIP's datetime form, in UTC to the millisecond: ``20261122120000.000``."""
    t = value.astimezone(UTC)
    return (
        f"{t.year:04d}{t.month:02d}{t.day:02d}{t.hour:02d}{t.minute:02d}{t.second:02d}"
        f".{t.microsecond // 1000:03d}"
    )


def reporting_unit(airframes: tuple[str, ...]) -> str:
    """The reporting unit's name: ``Fischer26E-<airframe>``.

    A track fused from several airframes names them all, sorted, joined by ``+``
    (``Fischer26E-F26E-001+F26E-002``), so SLB's operator sees every contributor in the one
    field it shows; past ``NAME_MAX_CHARS`` the first is named with a count of the others.
    A track without airframes (none recorded) is reported by ``Fischer26E`` alone.
    """
    names = sorted(set(airframes))
    if not names:
        return REPORTER_PREFIX
    whole = f"{REPORTER_PREFIX}-{'+'.join(names)}"
    if len(whole) <= NAME_MAX_CHARS:
        return whole
    first = f"{REPORTER_PREFIX}-{names[0]}"
    if len(names) == 1:
        return _clip(first, NAME_MAX_CHARS)
    others = f"+{len(names) - 1} more"
    return _clip(first, NAME_MAX_CHARS - len(others)) + others


def _clip(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[:limit]


def _at_least(table: tuple[tuple[float, str], ...], value: float) -> str:
    for floor, code in table:
        if value >= floor:
            return code
    return table[-1][1]


def _reporting_data(
    event: Detection | Track, observed: datetime, airframes: tuple[str, ...]
) -> dict[str, Any]:
    is_track = isinstance(event, Track)
    accuracy = _at_least(ACCURACY, event.confidence)
    lost = False
    if isinstance(event, Track):
        lost = event.status in ("lost", "merged")  # a merged track's object lives on elsewhere
        if accuracy == "2" and (len(set(airframes)) > 1 or len(set(event.sensors)) > 1):
            accuracy = "1"  # corroborated: several airframes or sensors agree
    return {
        "cat_code": "INFER" if is_track else "REP",
        "rep_dttm": jc3iedm_time(event.time),
        "timing_cat_code": "RDABST",
        "absolute_timing": {
            "effctv_start_dttm": jc3iedm_time(observed),
            # A lost track's last position held until it was last seen; others until the next.
            "effctv_end_dttm": jc3iedm_time(observed) if lost else None,
        },
        "rep_org_name_txt": reporting_unit(airframes),
        "source_type_code": "RPV",
        # B, usually reliable: our own airframes' sensors, whose error model we know.
        "reliability_code": "B",
        "credibility_code": _at_least(CREDIBILITY, event.confidence),
        "acc_code": accuracy,
        "confidence_pct": round(event.confidence * 100.0, 2),
    }


def _object_item(codes: ClassCodes, item_id: str, name: str) -> dict[str, Any]:
    return {
        "obj_item_id": item_id,
        "cat_code": codes.item_cat_code,
        "name_txt": _clip(name, NAME_MAX_CHARS),
        "materiel": {"cat_code": "NOS"} if codes.item_cat_code == "MA" else None,
        "organisation": {"cat_code": "UN"} if codes.item_cat_code == "OR" else None,
    }


def _object_type(codes: ClassCodes, name: str) -> dict[str, Any]:
    is_materiel = codes.item_cat_code == "MA"
    unit = codes.unit_type
    return {
        "cat_code": codes.item_cat_code,
        "decoy_ind_code": "NO",
        "name_txt": _clip(name, NAME_MAX_CHARS),
        "materiel_type": {"cat_code": "EQ"} if is_materiel else None,
        "equipment_type": (
            {"cat_code": codes.equipment_type} if codes.equipment_type is not None else None
        ),
        "weapon_type": {"cat_code": codes.weapon_type} if codes.weapon_type else None,
        "vehicle_type": {"cat_code": codes.vehicle_type} if codes.vehicle_type else None,
        "aircraft_type": (
            {"cat_code": codes.aircraft_type, "manning_code": "UNMANN", "mil_civ_code": "MIL"}
            if codes.aircraft_type
            else None
        ),
        "unit_type": (
            {"cat_code": unit[0], "arm_cat_code": unit[1], "size_code": unit[2]}
            if unit is not None
            else None
        ),
    }


def _location(position: Position) -> dict[str, Any]:
    vertical = None
    if position.alt_msl_m is not None:
        vertical = {"ref_code": "MNSLVL", "dim": position.alt_msl_m}
    elif position.alt_hae_m is not None:
        vertical = {"ref_code": "WGS84R", "dim": position.alt_hae_m}
    return {
        "cat_code": "PT",
        "point_cat_code": "ABS",
        "abs_point_cat_code": "GEOGPT",
        "lat_coord": position.lat_deg,
        "long_coord": position.lon_deg,
        "vertical_distance": vertical,
    }


def _label(object_class: str, subtype: str) -> str:
    return subtype.strip() or object_class.replace("_", " ").strip() or "unknown"


def object_item_payload(event: Detection | Track) -> dict[str, Any]:
    """The SLB document of ``event``: plain JSON types, keys exactly the schema's.

    Raises ``ValueError`` naming the event when its id (or its track's) is longer than 256
    characters: it would not fit the schema, nor sensibly an ``Idempotency-Key`` header.
    """
    for what, value in (("event id", event.event_id), ("track id", getattr(event, "track_id", ""))):
        if len(value) > _ID_MAX_CHARS:
            raise ValueError(f"{what} {value[:40]!r}...: longer than {_ID_MAX_CHARS} characters")
    codes = CLASSES.get(event.object_class, UNKNOWN_CLASS)
    label = _label(event.object_class, event.subtype)
    if isinstance(event, Track):
        airframes = event.airframes
        observed = event.last_seen
        item_id = f"fg:track:{event.track_id}"
        name = f"{label} {event.track_id}"
        hostility = HOSTILITY[event.hostility]
        placement = {
            "horz_acc_dim": event.cep50_m,
            "horz_acc_90_dim": event.cep90_m,
            "brng_angle": event.course_deg,
            "speed_rate": event.speed_mps,
        }
        sensors = event.sensors
        track: dict[str, Any] | None = {
            "track_id": event.track_id,
            "status": event.status,
            "detection_count": event.detection_count,
            "first_seen_dttm": jc3iedm_time(event.first_seen),
        }
    else:
        airframes = (event.airframe,)
        observed = event.time
        item_id = f"fg:detection:{event.event_id}"
        name = f"{label} ({event.airframe} {event.sensor.value.upper()})"
        hostility = codes.detection_hostility
        placement = {
            "horz_acc_dim": CEP50_PER_SIGMA * event.sigma_h_m,
            "horz_acc_90_dim": CEP90_PER_SIGMA * event.sigma_h_m,
            "brng_angle": None,
            "speed_rate": None,
        }
        sensors = (event.sensor,)
        track = None
    return {
        "schema": SCHEMA_ID,
        "event_id": event.event_id,
        "late_by_s": event.late_by_s,
        "reporting_data": _reporting_data(event, observed, airframes),
        "object_item": _object_item(codes, item_id, name),
        "object_type": _object_type(codes, label),
        "hostility_status": {"code": hostility},
        "location": _location(event.position),
        "object_item_location": placement,
        "fischer": {
            "kind": event.kind.value,
            "object_class": _clip(event.object_class, _TEXT_MAX),
            "subtype": _clip(event.subtype, _TEXT_MAX),
            "airframes": [_clip(a, _TEXT_MAX) for a in airframes[:_LIST_MAX]],
            "sensors": [sensor.value for sensor in sensors[:_LIST_MAX]],
            "track": track,
        },
    }


def encode_object_item(event: Detection | Track) -> bytes:
    """The document as compact UTF-8 JSON.

    Raises ``ValueError`` naming the event when a number is not finite (JSON has no NaN or
    infinity) or its id is too long, so a broken value is refused rather than sent.
    """
    try:
        text = json.dumps(
            object_item_payload(event),
            allow_nan=False,
            ensure_ascii=False,
            separators=(",", ":"),
        )
    except ValueError as exc:
        raise ValueError(
            f"{event.kind.value} {event.event_id[:64]}: cannot encode: {exc}"
        ) from None
    return text.encode("utf-8")
