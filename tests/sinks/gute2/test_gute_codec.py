"""The GUTE II handoff document: valid against its schema, exact, and a cue only."""

from __future__ import annotations

import json
import math
import re
from datetime import UTC, datetime, timedelta, timezone
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jsonschema import Draft202012Validator
from pydantic import ValidationError

from gateway.contract import sample_events
from gateway.domain.peertext import Provenance
from gateway.events import (
    BlueSourceCount,
    Deconfliction,
    EffectorOption,
    EventKind,
    Handoff,
    Position,
    Sensor,
    Track,
)
from sinks.gute2.codec import (
    SCHEMA_ID,
    SCHEMA_VERSIONS,
    encode_handoff,
    handoff_payload,
    load_schema,
    schema_for,
)

SCHEMA = load_schema()
#: What version 2 added to ``deconfliction`` (the provenance of the blue-force picture).
V2_DECONFLICTION = (
    "nearest_blue_callsign_provenance",
    "nearest_blue_source",
    "nearest_blue_provenance",
    "blue_sources",
)
VALIDATOR = Draft202012Validator(SCHEMA, format_checker=Draft202012Validator.FORMAT_CHECKER)
SAMPLE = sample_events(frozenset({EventKind.HANDOFF}))[0]
assert isinstance(SAMPLE, Handoff)

#: Words that would make a field an instruction to an effector rather than a cue.
COMMAND_WORDS = re.compile(
    r"(^|_)(fire|engage|engagement|launch|shoot|kill|release|command|order|execute|"
    r"weapons|arm|authorised|authorized|authorisation_granted|cleared_hot)(_|$)"
)

texts = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=20)
ids = st.text("ABCDEFGHJK0123456789-", min_size=1, max_size=16)
times = st.datetimes(
    min_value=datetime(2000, 1, 1),  # noqa: DTZ001 - hypothesis takes naive bounds
    max_value=datetime(2100, 1, 1),  # noqa: DTZ001 - the zone comes from timezones=
    timezones=st.just(UTC),
)
positions = st.builds(
    Position,
    lat_deg=st.floats(-90, 90),
    lon_deg=st.floats(-180, 180),
    alt_msl_m=st.none() | st.floats(-500, 20_000),
    alt_hae_m=st.none() | st.floats(-500, 20_000),
    alt_rel_home_m=st.none() | st.floats(-500, 20_000),
)
tracks = st.builds(
    Track,
    event_id=ids,
    track_id=ids,
    time=times,
    object_class=texts,
    subtype=texts,
    confidence=st.floats(0, 1),
    class_conflict=st.floats(0, 1),
    position=positions,
    cep50_m=st.floats(0, 1e5),
    cep90_m=st.floats(0, 1e5),
    speed_mps=st.none() | st.floats(0, 1000),
    course_deg=st.none() | st.floats(0, 360, exclude_max=True),
    airframes=st.lists(ids, max_size=3).map(tuple),
    sensors=st.lists(st.sampled_from(list(Sensor)), max_size=3).map(tuple),
    first_seen=times,
    last_seen=times,
)
options = st.builds(
    EffectorOption,
    effector=ids,
    deconfliction_clear=st.booleans(),
    danger_close_m=st.floats(0, 1e4),
)
deconflictions = st.builds(
    Deconfliction,
    clear=st.booleans(),
    nearest_blue_uid=st.none() | ids,
    nearest_blue_callsign=st.none() | texts,
    nearest_blue_m=st.none() | st.floats(0, 1e6),
    blue_units_considered=st.integers(0, 10_000),
    nearest_blue_callsign_provenance=st.none() | texts,
    nearest_blue_source=st.none() | ids,
    nearest_blue_provenance=st.none() | st.sampled_from(list(Provenance)),
    blue_sources=st.lists(
        st.builds(
            BlueSourceCount,
            source=ids,
            provenance=st.sampled_from(list(Provenance)),
            units=st.integers(0, 10_000),
        ),
        max_size=3,
    ).map(tuple),
)
handoffs = st.builds(
    Handoff,
    event_id=ids,
    handoff_id=ids,
    revision=st.integers(0, 1000),
    time=times,
    battery=ids,
    battery_position=positions,
    track=tracks,
    range_m=st.floats(0, 1e6),
    bearing_deg=st.floats(0, 360, exclude_max=True),
    recommended_effector=st.none() | ids,
    options=st.lists(options, max_size=4).map(tuple),
    deconfliction=deconflictions,
)


def resolve(node: dict[str, Any]) -> dict[str, Any]:
    ref = node.get("$ref")
    if ref is None:
        return node
    target: Any = SCHEMA
    for part in ref.removeprefix("#/").split("/"):
        target = target[part]
    return resolve(target)


def assert_keys_match(document: Any, node: dict[str, Any], where: str = "") -> None:
    """Every object in ``document`` has exactly the properties its schema node lists."""
    node = resolve(node)
    if isinstance(document, dict):
        assert set(document) == set(node["properties"]), where or "/"
        for key, value in document.items():
            assert_keys_match(value, node["properties"][key], f"{where}/{key}")
    elif isinstance(document, list) and "items" in node:
        for i, item in enumerate(document):
            assert_keys_match(item, node["items"], f"{where}/{i}")


def every_key(node: Any) -> list[str]:
    """Every property name anywhere in a schema or a document."""
    found: list[str] = []
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "properties" and isinstance(value, dict):
                found += list(value)
            elif not key.startswith("$") and key not in ("const", "enum"):
                found.append(key)
            found += every_key(value)
    elif isinstance(node, list):
        for item in node:
            found += every_key(item)
    return found


def object_schemas(node: Any) -> list[dict[str, Any]]:
    found: list[dict[str, Any]] = []
    if isinstance(node, dict):
        if node.get("type") == "object":
            found.append(node)
        for value in node.values():
            found += object_schemas(value)
    return found


class TestSchema:
    """The shipped schema pins the document's shape and its one safety constant."""

    def test_is_valid_draft_2020_12(self) -> None:
        Draft202012Validator.check_schema(SCHEMA)
        assert SCHEMA["$schema"] == "https://json-schema.org/draft/2020-12/schema"

    def test_operator_authorisation_is_a_required_constant_true(self) -> None:
        assert SCHEMA["properties"]["operator_authorisation_required"]["const"] is True
        assert "operator_authorisation_required" in SCHEMA["required"]
        document = handoff_payload(SAMPLE)
        document["operator_authorisation_required"] = False
        assert not VALIDATOR.is_valid(document)

    def test_every_object_forbids_other_properties_and_requires_all_of_its_own(self) -> None:
        objects = object_schemas(SCHEMA)
        assert len(objects) >= 6
        for node in objects:
            assert node["additionalProperties"] is False
            assert set(node["required"]) == set(node["properties"])

    def test_an_added_command_field_is_refused(self) -> None:
        for extra in ({"fire": True}, {"engage": "now"}, {"command": "release"}):
            assert not VALIDATOR.is_valid({**handoff_payload(SAMPLE), **extra})

    def test_no_property_anywhere_is_command_like(self) -> None:
        """Neither the schema nor a document has a field that could order an effector."""
        names = every_key(SCHEMA["properties"]) + every_key(SCHEMA["$defs"])
        names += every_key(handoff_payload(SAMPLE))
        assert "operator_authorisation_required" in names
        assert [n for n in names if COMMAND_WORDS.search(n)] == []


class TestPayload:
    """``handoff_payload`` writes exactly the schema's document."""

    def test_the_sample_validates_and_has_the_schemas_keys(self) -> None:
        document = handoff_payload(SAMPLE)
        VALIDATOR.validate(document)
        assert_keys_match(document, SCHEMA)
        assert document["schema"] == SCHEMA_ID
        assert document["operator_authorisation_required"] is True

    def test_shape(self) -> None:
        document = handoff_payload(SAMPLE)
        assert document["time"] == "2026-11-22T12:00:00.000Z"
        assert document["battery"] == {
            "id": "GUTE-1",
            "position": {"lat_deg": 59.34, "lon_deg": 18.05, "alt_msl_m": None, "alt_hae_m": None},
        }
        assert document["track"]["track_id"] == "T1"
        assert document["options"] == [
            {"effector": "TRACKFIRE_30MM", "deconfliction_clear": True, "danger_close_m": 400.0}
        ]
        assert document["deconfliction"]["blue_units_considered"] == 0
        assert json.loads(encode_handoff(SAMPLE)) == document

    @settings(max_examples=150, deadline=None)
    @given(handoffs)
    def test_any_handoff_validates_with_exact_keys(self, handoff: Handoff) -> None:
        document = json.loads(encode_handoff(handoff))
        VALIDATOR.validate(document)
        assert_keys_match(document, SCHEMA)
        assert document["operator_authorisation_required"] is True
        assert document["handoff_id"] == handoff.handoff_id
        assert document["revision"] == handoff.revision
        assert document["idempotency_key"] == handoff.event_id
        assert document["time"].endswith("Z")

    def test_the_blue_force_picture_says_where_it_came_from(self) -> None:
        check = Deconfliction(
            clear=False,
            nearest_blue_uid="ANDROID-RED",
            nearest_blue_callsign="WEAPONS FREE - ENGAGE AUTHORI...",
            nearest_blue_m=110.0,
            blue_units_considered=2,
            nearest_blue_callsign_provenance="unauthenticated CoT callsign",
            nearest_blue_source="atak-mesh",
            nearest_blue_provenance=Provenance.UNAUTHENTICATED,
            blue_sources=(
                BlueSourceCount(source="atak-mesh", provenance=Provenance.UNAUTHENTICATED, units=1),
                BlueSourceCount(source="cuas", provenance=Provenance.CONFIGURED, units=1),
            ),
        )
        document = handoff_payload(SAMPLE.model_copy(update={"deconfliction": check}))
        VALIDATOR.validate(document)
        blue = document["deconfliction"]
        assert blue["nearest_blue_callsign_provenance"] == "unauthenticated CoT callsign"
        assert (blue["nearest_blue_source"], blue["nearest_blue_provenance"]) == (
            "atak-mesh",
            "unauthenticated",
        )
        assert blue["blue_sources"] == [
            {"source": "atak-mesh", "provenance": "unauthenticated", "units": 1},
            {"source": "cuas", "provenance": "configured", "units": 1},
        ]

    def test_version_1_documents_stay_readable(self) -> None:
        """Schema 1 still ships: a document written before provenance validates against it."""
        old = load_schema(1)
        Draft202012Validator.check_schema(old)
        document = handoff_payload(SAMPLE)
        document["schema"] = "fischer-gateway/gute2-handoff/1"
        for key in V2_DECONFLICTION:
            del document["deconfliction"][key]
        for key in ("status", "superseded_by", "note"):
            del document[key]
        Draft202012Validator(old, format_checker=Draft202012Validator.FORMAT_CHECKER).validate(
            document
        )
        assert not VALIDATOR.is_valid(document)  # and version 2 tells the two apart
        with pytest.raises(ValueError, match="no GUTE II handoff schema version 3"):
            load_schema(3)

    def test_times_are_utc_whatever_the_events_zone(self) -> None:
        cet = datetime(2026, 11, 22, 13, 0, tzinfo=timezone(timedelta(hours=1)))
        document = handoff_payload(SAMPLE.model_copy(update={"time": cet}))
        assert document["time"] == "2026-11-22T12:00:00.000Z"

    def test_an_event_cannot_ask_for_no_operator(self) -> None:
        with pytest.raises(ValidationError):
            Handoff.model_validate(
                {**SAMPLE.model_dump(), "operator_authorisation_required": False}
            )

    def test_a_non_finite_number_is_refused_naming_the_handoff(self) -> None:
        broken = SAMPLE.model_copy(
            update={
                # Built without validation (as a hot path may build events): a Position's own
                # check refuses it, and the encoder must not rely on that.
                "battery_position": Position.model_construct(
                    lat_deg=59.0, lon_deg=18.0, alt_msl_m=math.inf
                )
            }
        )
        with pytest.raises(ValueError, match="handoff c-ho: cannot encode"):
            encode_handoff(broken)


class TestVersions:
    """Version 2 says when a cue is superseded; version 1's documents are still readable."""

    def test_a_superseded_revision_says_so_and_names_the_survivors_cue(self) -> None:
        revision = SAMPLE.model_copy(
            update={
                "event_id": f"{SAMPLE.handoff_id}-r1",
                "revision": 1,
                "status": "superseded",
                "superseded_by": "HO-T2-GUTE-1",
                "note": "track T1 merged into T2",
                "recommended_effector": None,
            }
        )
        document = handoff_payload(revision)
        VALIDATOR.validate(document)
        assert document["schema"] == SCHEMA_ID == "fischer-gateway/gute2-handoff/2"
        assert document["status"] == "superseded"
        assert document["superseded_by"] == "HO-T2-GUTE-1"
        assert document["note"] == "track T1 merged into T2"

    def test_a_withdrawn_revision_says_why_and_offers_nothing(self) -> None:
        revision = SAMPLE.model_copy(
            update={
                "event_id": f"{SAMPLE.handoff_id}-r2",
                "revision": 2,
                "status": "withdrawn",
                "note": "track T1 lost: no detection since 2026-11-22T12:00:00Z",
                "recommended_effector": None,
                "options": (),
            }
        )
        document = handoff_payload(revision)
        VALIDATOR.validate(document)
        assert (document["status"], document["superseded_by"]) == ("withdrawn", None)
        assert (document["recommended_effector"], document["options"]) == (None, [])
        assert document["note"].startswith("track T1 lost")
        assert document["operator_authorisation_required"] is True

    def test_a_status_outside_the_list_is_refused(self) -> None:
        document = handoff_payload(SAMPLE) | {"status": "engage"}
        assert not VALIDATOR.is_valid(document)

    def test_a_version_1_document_is_read_by_its_own_schema(self) -> None:
        document = handoff_payload(SAMPLE)
        for key in ("status", "superseded_by", "note"):
            del document[key]
        for key in V2_DECONFLICTION:
            del document["deconfliction"][key]
        document["schema"] = "fischer-gateway/gute2-handoff/1"
        assert set(SCHEMA_VERSIONS) == {"fischer-gateway/gute2-handoff/1", SCHEMA_ID}
        old = schema_for(document)
        assert old["properties"]["schema"]["const"] == "fischer-gateway/gute2-handoff/1"
        Draft202012Validator(old).validate(document)
        assert not VALIDATOR.is_valid(document)  # not a version 2 document
        assert schema_for({"schema": "nonsense"}) == SCHEMA

    def test_an_unknown_version_is_named(self) -> None:
        with pytest.raises(KeyError, match="gute2-handoff/9"):
            load_schema("fischer-gateway/gute2-handoff/9")
