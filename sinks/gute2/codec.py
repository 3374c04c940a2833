"""GUTE II track handoff: the JSON document a counter-UAS battery receives for one cue.

A handoff is a *cue*, never an order. The document carries the fused track, its range and
bearing from the battery, the effector the table recommends (or none), each effector offered
with its own danger-close deconfliction, and the blue-force check. It has no field that could
command an effector: ``operator_authorisation_required`` is always ``true`` (a ``const`` in
the schema), the schema forbids any property it does not list, and authorising an engagement
stays with the battery's human operator.

The schema ships as package data (``sinks/gute2/schemas/gute2-handoff.schema.json``, JSON
Schema draft 2020-12); ``load_schema`` reads it. ``SCHEMA_ID`` versions the document: a change
of shape is a new version, never a silent edit.

Version 2 adds where the blue-force picture came from (the nearest unit's source, provenance
and what its callsign is, "unauthenticated CoT callsign", and the current units counted per
source and provenance, ``blue_sources``) and the cue's own ``status``, ``superseded_by`` and
``note`` (a cue superseded when its track merged into another, withdrawn when its track was
lost). Version 1's schema still ships
(``gute2-handoff-1.schema.json``, ``load_schema(1)``), so a document written before stays
readable and checkable, and ``schema_for`` picks a document's own.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from importlib.resources import files
from typing import Any

from gateway.events import Deconfliction, EffectorOption, Handoff, Position, Track

__all__ = [
    "SCHEMA_ID",
    "SCHEMA_VERSION",
    "SCHEMA_VERSIONS",
    "encode_handoff",
    "handoff_payload",
    "load_schema",
    "schema_for",
]

#: The ``schema`` member of every document written now; its last part is the version.
SCHEMA_ID = "fischer-gateway/gute2-handoff/2"
SCHEMA_VERSION = 2
#: Every version a reader understands, by ``schema`` member, and its schema resource.
SCHEMA_VERSIONS = {
    "fischer-gateway/gute2-handoff/1": "schemas/gute2-handoff-1.schema.json",
    SCHEMA_ID: "schemas/gute2-handoff.schema.json",
}


def load_schema(version: int | str = SCHEMA_ID) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of ``version``, read from package data.

    ``version`` is a number (1, 2) or a document's ``schema`` member; the current version by
    default. An unknown number raises ``ValueError``, an unknown member ``KeyError``, each
    naming it.
    """
    if isinstance(version, int):
        if f"fischer-gateway/gute2-handoff/{version}" not in SCHEMA_VERSIONS:
            known = ", ".join(sid.rsplit("/", 1)[1] for sid in SCHEMA_VERSIONS)
            raise ValueError(f"no GUTE II handoff schema version {version}; known: {known}")
        version = f"fischer-gateway/gute2-handoff/{version}"
    try:
        resource = SCHEMA_VERSIONS[version]
    except KeyError:
        raise KeyError(f"unknown GUTE II handoff schema {version!r}") from None
    text = files("sinks.gute2").joinpath(resource).read_text(encoding="utf-8")
    schema: dict[str, Any] = json.loads(text)
    return schema


def schema_for(document: object) -> dict[str, Any]:
    """The schema of ``document``'s own version (its ``schema`` member); the current one
    when it names none we know, so validation then reports the mismatch."""
    named = document.get("schema") if isinstance(document, dict) else None
    return load_schema(named if isinstance(named, str) and named in SCHEMA_VERSIONS else SCHEMA_ID)


def _time(value: datetime) -> str:
    """UTC, ISO 8601, millisecond precision, ``Z``: ``2026-11-22T12:00:00.000Z``."""
    return value.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _position(position: Position) -> dict[str, Any]:
    return {
        "lat_deg": position.lat_deg,
        "lon_deg": position.lon_deg,
        "alt_msl_m": position.alt_msl_m,
        "alt_hae_m": position.alt_hae_m,
    }


def _track(track: Track) -> dict[str, Any]:
    return {
        "track_id": track.track_id,
        "object_class": track.object_class,
        "subtype": track.subtype,
        "confidence": track.confidence,
        "class_conflict": track.class_conflict,
        "position": _position(track.position),
        "cep50_m": track.cep50_m,
        "cep90_m": track.cep90_m,
        "speed_mps": track.speed_mps,
        "course_deg": track.course_deg,
        "first_seen": _time(track.first_seen),
        "last_seen": _time(track.last_seen),
        "airframes": list(track.airframes),
        "sensors": [sensor.value for sensor in track.sensors],
    }


def _option(option: EffectorOption) -> dict[str, Any]:
    return {
        "effector": option.effector,
        "deconfliction_clear": option.deconfliction_clear,
        "danger_close_m": option.danger_close_m,
    }


def _deconfliction(result: Deconfliction) -> dict[str, Any]:
    return {
        "clear": result.clear,
        "nearest_blue_uid": result.nearest_blue_uid,
        "nearest_blue_callsign": result.nearest_blue_callsign,
        "nearest_blue_m": result.nearest_blue_m,
        "blue_units_considered": result.blue_units_considered,
        "blue_picture_complete": result.blue_picture_complete,
        "nearest_blue_callsign_provenance": result.nearest_blue_callsign_provenance,
        "nearest_blue_source": result.nearest_blue_source,
        "nearest_blue_provenance": (
            None if result.nearest_blue_provenance is None else result.nearest_blue_provenance.value
        ),
        "blue_sources": [
            {"source": s.source, "provenance": s.provenance.value, "units": s.units}
            for s in result.blue_sources
        ],
    }


def handoff_payload(handoff: Handoff) -> dict[str, Any]:
    """The GUTE II document of ``handoff``: plain JSON types, keys exactly the schema's.

    ``operator_authorisation_required`` is written as the constant ``True``, not copied from
    the event, so no input can produce a document that does not ask for the operator.
    """
    return {
        "schema": SCHEMA_ID,
        "handoff_id": handoff.handoff_id,
        "revision": handoff.revision,
        "idempotency_key": handoff.event_id,
        "status": handoff.status,
        "superseded_by": handoff.superseded_by,
        "note": handoff.note,
        "time": _time(handoff.time),
        "battery": {"id": handoff.battery, "position": _position(handoff.battery_position)},
        "track": _track(handoff.track),
        "range_m": handoff.range_m,
        "bearing_deg": handoff.bearing_deg,
        "recommended_effector": handoff.recommended_effector,
        "options": [_option(option) for option in handoff.options],
        "deconfliction": _deconfliction(handoff.deconfliction),
        "operator_authorisation_required": True,
    }


def encode_handoff(handoff: Handoff) -> bytes:
    """The document as compact UTF-8 JSON.

    Raises ``ValueError`` naming the handoff when a number is not finite (JSON has no NaN or
    infinity), so a broken value is refused rather than sent as something it is not.
    """
    try:
        text = json.dumps(
            handoff_payload(handoff), allow_nan=False, ensure_ascii=False, separators=(",", ":")
        )
    except ValueError as exc:
        raise ValueError(f"handoff {handoff.event_id}: cannot encode: {exc}") from None
    return text.encode("utf-8")
