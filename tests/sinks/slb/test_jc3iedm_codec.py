"""The SLB object item document (JC3IEDM): valid against its schema, exact, and mapped right."""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime, timedelta, timezone
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jsonschema import Draft202012Validator

from gateway.contract import sample_events
from gateway.events import Detection, EventKind, Position, Sensor, Track
from sinks.slb.jc3iedm import (
    CEP50_PER_SIGMA,
    CEP90_PER_SIGMA,
    CLASSES,
    HOSTILITY,
    NAME_MAX_CHARS,
    SCHEMA_ID,
    encode_object_item,
    jc3iedm_time,
    load_schema,
    object_item_payload,
    reporting_unit,
)

SCHEMA = load_schema()
VALIDATOR = Draft202012Validator(SCHEMA, format_checker=Draft202012Validator.FORMAT_CHECKER)
DETECTION, TRACK = sample_events(frozenset({EventKind.DETECTION, EventKind.TRACK}))
assert isinstance(DETECTION, Detection)
assert isinstance(TRACK, Track)

texts = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=20)
ids = st.text("ABCDEFGHJK0123456789-", min_size=1, max_size=16)
classes = st.sampled_from([*CLASSES, "other", "class_9", ""]) | texts
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
)
detections = st.builds(
    Detection,
    event_id=ids,
    airframe=ids,
    time=times,
    sensor=st.sampled_from(list(Sensor)),
    object_class=classes,
    subtype=texts,
    confidence=st.floats(0, 1),
    position=positions,
    sigma_h_m=st.floats(0, 1e5),
    late_by_s=st.none() | st.floats(0, 1e6),
)
tracks = st.builds(
    Track,
    event_id=ids,
    track_id=ids,
    time=times,
    status=st.sampled_from(["created", "updated", "lost"]),
    object_class=classes,
    subtype=texts,
    confidence=st.floats(0, 1),
    position=positions,
    cep50_m=st.floats(0, 1e5),
    cep90_m=st.floats(0, 1e5),
    speed_mps=st.none() | st.floats(0, 1000),
    course_deg=st.none() | st.floats(0, 360, exclude_max=True),
    detection_count=st.integers(0, 10_000),
    airframes=st.lists(ids, max_size=40).map(lambda a: tuple(sorted(set(a)))),
    sensors=st.lists(st.sampled_from(list(Sensor)), max_size=3).map(tuple),
    first_seen=times,
    last_seen=times,
    hostility=st.sampled_from(list(HOSTILITY)),
    late_by_s=st.none() | st.floats(0, 1e6),
)


def resolve(node: dict[str, Any]) -> dict[str, Any]:
    ref = node.get("$ref")
    if ref is None:
        return node
    target: Any = SCHEMA
    for part in ref.removeprefix("#/").split("/"):
        target = target[part]
    return resolve(target)


def object_branch(node: dict[str, Any]) -> dict[str, Any] | None:
    """The object schema of ``node``: itself, its ``$ref``, or the object arm of ``anyOf``."""
    node = resolve(node)
    if node.get("type") == "object":
        return node
    for arm in node.get("anyOf", []):
        found = object_branch(arm)
        if found is not None:
            return found
    return None


def assert_keys_match(document: Any, node: dict[str, Any], where: str = "/") -> None:
    """Every object in ``document`` has exactly the properties its schema node lists."""
    if isinstance(document, dict):
        schema = object_branch(node)
        assert schema is not None, where
        assert set(document) == set(schema["properties"]), where
        for key, value in document.items():
            assert_keys_match(value, schema["properties"][key], f"{where}{key}/")


def object_schemas(node: Any) -> list[dict[str, Any]]:
    found: list[dict[str, Any]] = []
    if isinstance(node, dict):
        if node.get("type") == "object":
            found.append(node)
        for value in node.values():
            found += object_schemas(value)
    elif isinstance(node, list):
        for item in node:
            found += object_schemas(item)
    return found


def enum_values(name: str) -> set[str]:
    """The codes the schema allows for the ``cat_code`` (or other) property of ``$defs/name``."""
    properties = SCHEMA["$defs"][name]["properties"]
    key = "code" if "code" in properties else "cat_code"
    return set(properties[key]["enum"])


class TestSchema:
    """The shipped schema is strict: every object closed and complete, every code an enum."""

    def test_is_valid_draft_2020_12(self) -> None:
        Draft202012Validator.check_schema(SCHEMA)
        assert SCHEMA["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        assert SCHEMA["properties"]["schema"]["const"] == SCHEMA_ID

    def test_every_object_forbids_other_properties_and_requires_all_of_its_own(self) -> None:
        objects = object_schemas(SCHEMA)
        assert len(objects) == 1 + len(SCHEMA["$defs"])  # the root and every definition
        for node in objects:
            assert node["additionalProperties"] is False
            assert set(node["required"]) == set(node["properties"])

    def test_every_code_column_is_an_enum(self) -> None:
        for node in object_schemas(SCHEMA):
            for name, prop in node["properties"].items():
                if name.endswith("_code") or name == "code":
                    assert "enum" in prop, name

    def test_the_mapping_tables_use_only_codes_the_schema_allows(self) -> None:
        for codes in CLASSES.values():
            assert codes.item_cat_code in enum_values("object_item")
            assert codes.detection_hostility in enum_values("hostility_status")
            if codes.weapon_type:
                assert codes.weapon_type in enum_values("weapon_type")
            if codes.vehicle_type:
                assert codes.vehicle_type in enum_values("vehicle_type")
            if codes.aircraft_type:
                assert codes.aircraft_type in enum_values("aircraft_type")
        assert set(HOSTILITY.values()) <= enum_values("hostility_status")

    def test_an_added_member_is_refused(self) -> None:
        document = object_item_payload(TRACK)
        assert not VALIDATOR.is_valid({**document, "priority": "flash"})
        document["location"] = {**document["location"], "mgrs": "34WEP"}
        assert not VALIDATOR.is_valid(document)


class TestMapping:
    """Classes, hostility, accuracy and timing are written with the MIP codes."""

    def test_a_tank_detection_is_an_assumed_hostile_materiel_weapon_type_tank(self) -> None:
        tank = DETECTION.model_copy(update={"object_class": "tank", "subtype": "T-72B3"})
        document = object_item_payload(tank)
        assert document["object_item"] == {
            "obj_item_id": "fg:detection:c-det",
            "cat_code": "MA",
            "name_txt": "T-72B3 (F26E-001 EO)",
            "materiel": {"cat_code": "NOS"},
            "organisation": None,
        }
        kind = document["object_type"]
        assert kind["name_txt"] == "T-72B3"
        assert kind["materiel_type"] == {"cat_code": "EQ"}
        assert kind["equipment_type"] == {"cat_code": "WEPTYP"}
        assert kind["weapon_type"] == {"cat_code": "TANK"}
        assert kind["aircraft_type"] is None
        assert document["hostility_status"] == {"code": "AHO"}
        assert document["reporting_data"]["cat_code"] == "REP"
        assert document["reporting_data"]["rep_org_name_txt"] == "Fischer26E-F26E-001"

    def test_a_uav_is_an_unmanned_military_aircraft_type(self) -> None:
        document = object_item_payload(DETECTION)  # class uav
        assert document["object_type"]["aircraft_type"] == {
            "cat_code": "NKN",
            "manning_code": "UNMANN",
            "mil_civ_code": "MIL",
        }
        lancet = DETECTION.model_copy(update={"object_class": "loitering_munition"})
        aircraft = object_item_payload(lancet)["object_type"]["aircraft_type"]
        assert aircraft["cat_code"] == "FIXWNG"
        assert aircraft["manning_code"] == "UNMANN"

    def test_an_infantry_platoon_is_an_organisation_unit(self) -> None:
        platoon = TRACK.model_copy(update={"object_class": "infantry_platoon"})
        document = object_item_payload(platoon)
        assert document["object_item"]["cat_code"] == "OR"
        assert document["object_item"]["organisation"] == {"cat_code": "UN"}
        assert document["object_item"]["materiel"] is None
        assert document["object_type"]["unit_type"] == {
            "cat_code": "COMBAT",
            "arm_cat_code": "INF",
            "size_code": "PLT",
        }
        assert document["object_type"]["materiel_type"] is None

    def test_an_unknown_class_is_not_known_and_unknown_hostility(self) -> None:
        odd = DETECTION.model_copy(update={"object_class": "class_9"})
        document = object_item_payload(odd)
        assert document["object_item"]["cat_code"] == "NKN"
        assert document["object_type"]["cat_code"] == "NKN"
        assert document["hostility_status"] == {"code": "UNK"}
        VALIDATOR.validate(document)

    @pytest.mark.parametrize(("hostility", "code"), sorted(HOSTILITY.items()))
    def test_a_tracks_hostility_is_its_code(self, hostility: str, code: str) -> None:
        document = object_item_payload(TRACK.model_copy(update={"hostility": hostility}))
        assert document["hostility_status"]["code"] == code

    def test_detection_accuracy_is_cep50_and_the_90_percent_circle_from_sigma(self) -> None:
        placement = object_item_payload(DETECTION)["object_item_location"]
        assert placement["horz_acc_dim"] == pytest.approx(CEP50_PER_SIGMA * 15.0)
        assert placement["horz_acc_90_dim"] == pytest.approx(CEP90_PER_SIGMA * 15.0)
        # The constants are the circular normal's: sqrt(2 ln 2) and sqrt(2 ln 10).
        assert abs(CEP50_PER_SIGMA - math.sqrt(2 * math.log(2))) < 1e-4
        assert abs(CEP90_PER_SIGMA - math.sqrt(2 * math.log(10))) < 1e-4
        assert placement["brng_angle"] is None
        assert placement["speed_rate"] is None

    def test_a_track_carries_its_ceps_course_speed_and_is_inferred(self) -> None:
        moving = TRACK.model_copy(
            update={"course_deg": 135.0, "speed_mps": 10.0, "airframes": ("F26E-001",)}
        )
        document = object_item_payload(moving)
        assert document["object_item_location"] == {
            "horz_acc_dim": 10.0,
            "horz_acc_90_dim": 18.0,
            "brng_angle": 135.0,
            "speed_rate": 10.0,
        }
        assert document["object_item"]["obj_item_id"] == "fg:track:T1"
        data = document["reporting_data"]
        assert data["cat_code"] == "INFER"
        assert data["source_type_code"] == "RPV"
        assert data["timing_cat_code"] == "RDABST"
        assert data["confidence_pct"] == 80.0
        assert (data["credibility_code"], data["acc_code"]) == ("RPTPLA", "3")

    def test_a_corroborated_confident_track_is_confirmed(self) -> None:
        fused = TRACK.model_copy(update={"confidence": 0.95, "airframes": ("F26E-001", "F26E-002")})
        data = object_item_payload(fused)["reporting_data"]
        assert (data["credibility_code"], data["acc_code"]) == ("RPTFCT", "1")
        alone = object_item_payload(fused.model_copy(update={"airframes": ("F26E-001",)}))
        assert alone["reporting_data"]["acc_code"] == "2"

    def test_observation_and_report_times_and_a_lost_tracks_end(self) -> None:
        t = datetime(2026, 11, 22, 12, 0, 5, 250_000, tzinfo=UTC)
        seen = t - timedelta(seconds=4)
        lost = TRACK.model_copy(update={"time": t, "last_seen": seen, "status": "lost"})
        data = object_item_payload(lost)["reporting_data"]
        assert data["rep_dttm"] == "20261122120005.250"
        assert data["absolute_timing"] == {
            "effctv_start_dttm": "20261122120001.250",
            "effctv_end_dttm": "20261122120001.250",
        }
        live = object_item_payload(lost.model_copy(update={"status": "updated"}))
        assert live["reporting_data"]["absolute_timing"]["effctv_end_dttm"] is None

    def test_times_are_utc_whatever_the_events_zone(self) -> None:
        cet = datetime(2026, 11, 22, 13, 0, tzinfo=timezone(timedelta(hours=1)))
        assert jc3iedm_time(cet) == "20261122120000.000"

    def test_height_is_msl_or_else_ellipsoidal_or_absent(self) -> None:
        where = DETECTION.position
        msl = object_item_payload(DETECTION)["location"]["vertical_distance"]
        assert msl == {"ref_code": "MNSLVL", "dim": 250.0}
        hae = where.model_copy(update={"alt_msl_m": None, "alt_hae_m": 280.0})
        document = object_item_payload(DETECTION.model_copy(update={"position": hae}))
        assert document["location"]["vertical_distance"] == {"ref_code": "WGS84R", "dim": 280.0}
        flat = where.model_copy(update={"alt_msl_m": None})
        document = object_item_payload(DETECTION.model_copy(update={"position": flat}))
        assert document["location"]["vertical_distance"] is None
        assert (document["location"]["lat_coord"], document["location"]["long_coord"]) == (
            65.8252,
            21.6886,
        )

    def test_late_delivery_is_carried(self) -> None:
        late = DETECTION.model_copy(update={"late_by_s": 42.5})
        assert object_item_payload(late)["late_by_s"] == 42.5
        assert object_item_payload(DETECTION)["late_by_s"] is None


class TestReportingUnit:
    """One airframe names itself; a fused track names every airframe, within 100 characters."""

    def test_names(self) -> None:
        assert reporting_unit(("F26E-001",)) == "Fischer26E-F26E-001"
        assert reporting_unit(("F26E-002", "F26E-001")) == "Fischer26E-F26E-001+F26E-002"
        assert reporting_unit(()) == "Fischer26E"

    def test_many_airframes_fit_the_column(self) -> None:
        name = reporting_unit(tuple(f"F26E-{n:03d}" for n in range(40)))
        assert len(name) <= NAME_MAX_CHARS
        assert name == "Fischer26E-F26E-000+39 more"
        assert len(reporting_unit(("X" * 300,))) == NAME_MAX_CHARS


class TestEncoding:
    """What cannot be sent as it is, is refused, naming the event."""

    def test_a_non_finite_number_is_refused_naming_the_event(self) -> None:
        broken = DETECTION.model_copy(update={"sigma_h_m": math.inf})
        with pytest.raises(ValueError, match="detection c-det: cannot encode"):
            encode_object_item(broken)

    def test_an_overlong_id_is_refused(self) -> None:
        with pytest.raises(ValueError, match="longer than 256"):
            encode_object_item(DETECTION.model_copy(update={"event_id": "E" * 257}))

    def test_the_bytes_are_the_payload(self) -> None:
        assert json.loads(encode_object_item(TRACK)) == object_item_payload(TRACK)


class TestProperties:
    """Any Detection or Track gives a schema-valid document with exactly the schema's keys."""

    @settings(max_examples=150, deadline=None)
    @given(detections)
    def test_any_detection(self, detection: Detection) -> None:
        document = json.loads(encode_object_item(detection))
        VALIDATOR.validate(document)
        assert_keys_match(document, SCHEMA)
        assert document["event_id"] == detection.event_id
        assert document["reporting_data"]["cat_code"] == "REP"
        assert document["fischer"]["track"] is None

    @settings(max_examples=150, deadline=None)
    @given(tracks)
    def test_any_track(self, track: Track) -> None:
        document = json.loads(encode_object_item(track))
        VALIDATOR.validate(document)
        assert_keys_match(document, SCHEMA)
        assert document["object_item"]["obj_item_id"] == f"fg:track:{track.track_id}"
        assert document["hostility_status"]["code"] == HOSTILITY[track.hostility]
        assert document["fischer"]["track"]["status"] == track.status

    @settings(max_examples=50, deadline=None)
    @given(tracks)
    def test_a_document_is_a_function_of_its_event(self, track: Track) -> None:
        """A retry sends the same bytes under the same key: no clock inside."""
        assert encode_object_item(track) == encode_object_item(track.model_copy())
