"""The SWECCIS FAS documents: every one we write is valid against the shipped XSD (lxml),
orders are read exactly and checked field by field, and nothing a server sends raises
anything but ``DocumentError``."""

from __future__ import annotations

import contextlib
import math
import re
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from lxml import etree
from sweccis_peer import order_document

from gateway.contract import sample_events
from gateway.domain.geodesy import from_mgrs
from gateway.events import (
    ALT_MAX_M,
    ALT_MIN_M,
    Attitude,
    Detection,
    EventKind,
    OrderPriority,
    OrderTask,
    Position,
    Sensor,
    Telemetry,
    Track,
    Velocity,
)
from gateway.testing import fuzz_examples
from sinks.sweccis.fas import (
    NAMESPACE,
    SCHEMA_VERSIONS,
    Ack,
    Document,
    DocumentError,
    Fas,
    OrderDocument,
    Registered,
    encode_ack,
    encode_event,
    encode_register,
    load_schema,
    parse_document,
)

ROOT = Path(__file__).resolve().parents[3]
SCHEMA = etree.XMLSchema(etree.fromstring(load_schema()))
SCHEMA_2 = etree.XMLSchema(etree.fromstring(load_schema("2")))
NS = f"{{{NAMESPACE}}}"
NS2 = f"{{{SCHEMA_VERSIONS['2']}}}"
T0 = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)
SAMPLES = {e.kind: e for e in sample_events(frozenset(EventKind))}


def valid(payload: bytes) -> etree._Element:
    """The document, after asserting the XSD accepts it."""
    root = etree.fromstring(payload)
    assert SCHEMA.validate(root), SCHEMA.error_log
    return root


def schema_accepts(payload: bytes) -> bool:
    try:
        return bool(SCHEMA.validate(etree.fromstring(payload)))
    except etree.XMLSyntaxError:
        return False


def text(root: etree._Element, path: str) -> str | None:
    return root.findtext("/".join(NS + part for part in path.split("/")))


def find(root: etree._Element, path: str) -> etree._Element:
    found = root.find("/".join(NS + part for part in path.split("/")))
    assert found is not None, path
    return found


def telemetry(**update: Any) -> Telemetry:
    base = Telemetry(
        event_id="F26E-001-tel-ab12cd34-7",
        airframe="F26E-001",
        time=T0,
        position=Position(lat_deg=65.86, lon_deg=21.64, alt_msl_m=600.0, alt_rel_home_m=560.0),
        alt_agl_m=555.5,
        attitude=Attitude(roll_rad=0.1, pitch_rad=-0.05, yaw_rad=math.pi / 2),
        velocity=Velocity(north_mps=20.0, east_mps=-15.0, down_mps=0.5),
        heading_deg=90.0,
        groundspeed_mps=25.0,
        airspeed_mps=27.0,
        climb_mps=-0.5,
        gps_fix_type=3,
        satellites_visible=14,
        h_acc_m=1.2,
        battery_pct=76.0,
        battery_voltage_v=24.1,
        battery_current_a=11.5,
        battery_consumed_wh=120.0,
        battery_time_remaining_s=5400.0,
        endurance_remaining_min=88.0,
        ew_mode="active",
        mav_type=1,
        autopilot=3,
        is_armed=True,
        custom_mode=15,
        system_status=4,
        active_link="starlink",
    )
    return base.model_copy(update=update)


class TestEncoding:
    """Events to Intel, Logistics and Operations documents: valid and exact."""

    def test_a_detection_is_one_intel_document_with_its_fields(self) -> None:
        detection = SAMPLES[EventKind.DETECTION]
        assert isinstance(detection, Detection)
        detection = detection.model_copy(update={"subtype": "Orlan-10", "late_by_s": 42.5})
        (document,) = encode_event(detection)
        assert (document.fas, document.doc_id, document.event_id) == (
            Fas.INTEL,
            "c-det",
            "c-det",
        )
        root = valid(document.payload)
        assert root.tag == f"{NS}Intel"
        assert root.get("version") == "1"
        assert text(root, "Detection/Time") == "2026-11-22T12:00:00.000Z"
        assert text(root, "Detection/Sensor") == "eo"
        assert text(root, "Detection/Subtype") == "Orlan-10"
        assert text(root, "Detection/LateByS") == "42.5"
        position = find(root, "Detection/Position")
        assert (position.get("latDeg"), position.get("lonDeg")) == ("65.8252", "21.6886")
        assert find(root, "Detection/Uncertainty").get("sigmaHM") == "15.0"

    def test_a_track_carries_ceps_hostility_kinematics_and_contributors(self) -> None:
        track = SAMPLES[EventKind.TRACK]
        assert isinstance(track, Track)
        track = track.model_copy(
            update={
                "hostility": "hostile",
                "speed_mps": 30.0,
                "course_deg": 225.0,
                "sensors": (Sensor.EO, Sensor.IR, Sensor.EO),
                "airframes": ("F26E-001", "F26E-002"),
                "detection_count": 7,
                "sidc": "SHAPMFQ----",
            }
        )
        root = valid(encode_event(track)[0].payload)
        assert text(root, "Track/Hostility") == "hostile"
        assert find(root, "Track/Uncertainty").attrib == {"cep50M": "10.0", "cep90M": "18.0"}
        assert find(root, "Track/Kinematics").attrib == {"speedMps": "30.0", "courseDeg": "225.0"}
        assert [e.text for e in find(root, "Track/Sensors")] == ["eo", "ir"]  # each once
        assert [e.text for e in find(root, "Track/Airframes")] == ["F26E-001", "F26E-002"]
        assert text(root, "Track/DetectionCount") == "7"
        assert text(root, "Track/LateByS") is None

    def test_a_merged_track_ends_as_lost_in_version_1(self) -> None:
        track = SAMPLES[EventKind.TRACK]
        assert isinstance(track, Track)
        merged = track.model_copy(update={"status": "merged", "merged_into": "T0"})
        root = valid(encode_event(merged)[0].payload)
        assert text(root, "Track/Status") == "lost"
        assert text(root, "Track/MergedInto") is None


class TestVersion2:
    """FAS version 2 publishes a merge as a merge; version 1 stays as it was, and valid."""

    def merged(self) -> Track:
        track = SAMPLES[EventKind.TRACK]
        assert isinstance(track, Track)
        return track.model_copy(update={"status": "merged", "merged_into": "T-0007"})

    def test_a_merged_track_is_merged_and_names_the_survivor(self) -> None:
        (document,) = encode_event(self.merged(), version="2")
        root = etree.fromstring(document.payload)
        assert SCHEMA_2.validate(root), SCHEMA_2.error_log
        assert root.tag == f"{{{SCHEMA_VERSIONS['2']}}}Intel"
        assert root.get("version") == "2"
        ns = f"{{{SCHEMA_VERSIONS['2']}}}"
        assert root.findtext(f"{ns}Track/{ns}Status") == "merged"
        assert root.findtext(f"{ns}Track/{ns}MergedInto") == "T-0007"
        # MergedInto comes right after Status, as the schema's sequence says.
        tags = [etree.QName(e).localname for e in root.find(f"{ns}Track")]
        assert tags[1:3] == ["Status", "MergedInto"]
        # A version 1 reader's schema refuses it: the version is a new namespace, not an edit.
        assert not SCHEMA.validate(root)

    def test_every_kind_and_control_document_is_valid_in_version_2(self) -> None:
        documents = [d.payload for e in SAMPLES.values() for d in _encodable(e, "2")]
        documents += [
            encode_register("r-1", "node-1", publish=[Fas.INTEL], version="2"),
            encode_ack("doc-1", "accepted", version="2"),
        ]
        assert len(documents) >= 5
        for payload in documents:
            root = etree.fromstring(payload)
            assert SCHEMA_2.validate(root), (payload[:80], SCHEMA_2.error_log)
            assert root.get("version") == "2"

    def test_other_statuses_carry_no_merged_into_and_version_1_is_unchanged(self) -> None:
        track = SAMPLES[EventKind.TRACK]
        assert isinstance(track, Track)
        for status in ("created", "updated", "lost"):
            event = track.model_copy(update={"status": status})
            v2 = etree.fromstring(encode_event(event, version="2")[0].payload)
            assert SCHEMA_2.validate(v2), SCHEMA_2.error_log
            assert v2.find(f"{NS2}Track/{NS2}MergedInto") is None
            v1 = encode_event(event)[0].payload
            assert encode_event(event, version="1")[0].payload == v1
            assert valid(v1).get("version") == "1"

    def test_a_merged_track_without_its_survivor_or_an_unknown_version_is_refused(self) -> None:
        orphan = self.merged().model_copy(update={"merged_into": None})
        with pytest.raises(ValueError, match="MergedInto"):
            encode_event(orphan, version="2")
        with pytest.raises(ValueError, match="version '3'"):
            encode_event(self.merged(), version="3")
        with pytest.raises(ValueError, match="version '3'"):
            load_schema("3")

    def test_version_2_control_documents_are_read_and_a_mismatch_is_refused(self) -> None:
        ns2 = SCHEMA_VERSIONS["2"]
        registered = parse_document(
            f'<Registered xmlns="{ns2}" version="2" ref="r-1"><Publish>Intel</Publish>'
            "</Registered>".encode(),
            source="s",
        )
        assert registered == Registered("r-1", frozenset({Fas.INTEL}), frozenset())
        assert parse_document(encode_ack("d-1", "accepted", version="2"), source="s") == Ack(
            "d-1", "accepted"
        )
        for wrong in (
            f'<Ack xmlns="{ns2}" version="1" ref="a" status="accepted"/>',
            f'<Ack xmlns="{NAMESPACE}" version="2" ref="a" status="accepted"/>',
            f'<Ack xmlns="{ns2}" version="2" ref="a" status="rejected">'
            f'<Reason xmlns="{NAMESPACE}">mixed</Reason></Ack>',
        ):
            with pytest.raises(DocumentError):
                parse_document(wrong.encode(), source="s")


def _encodable(event: object, version: str) -> list[Document]:
    try:
        return encode_event(event, version=version)  # type: ignore[arg-type]
    except ValueError:
        return []  # a kind no FAS carries

    def test_telemetry_is_a_logistics_and_an_operations_document(self) -> None:
        logistics, operations = encode_event(telemetry())
        assert (logistics.fas, operations.fas) == (Fas.LOGISTICS, Fas.OPERATIONS)
        assert logistics.doc_id == "F26E-001-tel-ab12cd34-7/logistics"
        assert operations.doc_id == "F26E-001-tel-ab12cd34-7/operations"
        health = valid(logistics.payload)
        assert text(health, "AirframeHealth/SystemStatus") == "active"
        assert find(health, "AirframeHealth/Gps").attrib == {
            "fix": "fix_3d",
            "satellites": "14",
            "hAccM": "1.2",
        }
        assert text(health, "AirframeHealth/LinkInUse") == "starlink"
        assert find(health, "AirframeHealth/Battery").get("pct") == "76.0"
        assert text(health, "AirframeHealth/EnduranceRemainingMin") == "88.0"
        assert text(health, "AirframeHealth/EwMode") == "active"
        state = valid(operations.payload)
        assert find(state, "AirframeState/Position").get("altAglM") == "555.5"
        assert float(find(state, "AirframeState/Attitude").get("yawDeg", "")) == pytest.approx(90)
        assert find(state, "AirframeState/Motion").get("eastMps") == "-15.0"
        assert find(state, "AirframeState/Mission").attrib == {
            "armed": "true",
            "mode": "GUIDED",
            "customMode": "15",
            "systemStatus": "active",
        }

    def test_telemetry_without_a_position_has_no_operations_document(self) -> None:
        documents = encode_event(telemetry(position=None))
        assert [d.fas for d in documents] == [Fas.LOGISTICS]

    def test_a_bare_telemetry_event_is_still_valid(self) -> None:
        bare = Telemetry(event_id="x-1", airframe="A", time=T0)
        (logistics,) = encode_event(bare)
        assert len(valid(logistics.payload)[0]) == 2  # Airframe and Time only

    def test_unknown_mavlink_values_are_named_unknown_and_modes_only_for_arduplane(self) -> None:
        _, operations = encode_event(telemetry(system_status=42, mav_type=2, gps_fix_type=99))
        mission = find(valid(operations.payload), "AirframeState/Mission")
        assert mission.get("systemStatus") == "unknown"
        assert mission.get("mode") is None  # a copter's mode 15 is not ArduPlane's GUIDED
        logistics, _ = encode_event(telemetry(gps_fix_type=99))
        assert find(valid(logistics.payload), "AirframeHealth/Gps").get("fix") == "unknown"

    def test_the_fas_can_be_left_out(self) -> None:
        assert [d.fas for d in encode_event(telemetry(), logistics=False)] == [Fas.OPERATIONS]
        assert encode_event(telemetry(), logistics=False, operations=False) == []

    @pytest.mark.parametrize(
        ("update", "field"),
        [
            ({"battery_voltage_v": math.nan}, "Battery/voltageV"),
            ({"climb_mps": math.inf}, "Motion/climbMps"),
            ({"airframe": "A\x01B"}, "Airframe"),
            ({"event_id": "has space"}, "@id"),
            ({"ew_mode": "jamming"}, "EwMode"),
            ({"satellites_visible": 300}, "Gps/satellites"),
        ],
    )
    def test_a_value_the_schema_cannot_hold_is_refused_by_name(
        self, update: dict[str, Any], field: str
    ) -> None:
        with pytest.raises(ValueError, match=re.escape(field)) as caught:
            encode_event(telemetry(**update))
        assert "telemetry" in str(caught.value)

    def test_kinds_without_a_fas_are_refused(self) -> None:
        for kind in (EventKind.HANDOFF, EventKind.BLUE_FORCE, EventKind.LINK_STATE):
            with pytest.raises(ValueError, match="no SWECCIS FAS"):
                encode_event(SAMPLES[kind])

    def test_control_documents_are_valid(self) -> None:
        register = valid(
            encode_register("r-1", "node-1", publish=[Fas.INTEL], subscribe=[Fas.ORDERS])
        )
        assert [e.text for e in register] == ["node-1", "Intel", "Orders"]
        valid(encode_ack("doc-1", "accepted"))
        ack = valid(encode_ack("doc-2", "rejected", "x" * 600))
        assert len(text(ack, "Reason") or "") == 512
        odd = valid(encode_ack("doc-3", "rejected", "bad \x00 byte \ud800"))
        assert text(odd, "Reason") == "bad \ufffd byte \ufffd"


def event_strategies(*, sane: bool) -> st.SearchStrategy[Any]:
    """Detections, tracks and telemetry. ``sane``: values the schema holds (as ingest makes
    them); otherwise anything the models allow (NaN, control characters, huge numbers)."""
    if sane:
        chars = st.characters(
            codec="utf-8", exclude_categories=("Cs", "Cc"), exclude_characters="\ufffe\uffff"
        )
        number: st.SearchStrategy[float] = st.floats(-1e6, 1e6)
        ids = st.text(st.characters(min_codepoint=33, max_codepoint=126), min_size=1, max_size=40)
        alt = st.floats(-1e4, 1e5)
        fix, sats, modes = st.integers(0, 8), st.integers(0, 255), st.integers(0, 2**32 - 1)
        ew = st.sampled_from(["permissive", "active", "heavy"])
    else:
        chars = st.characters(codec="utf-8")
        number = st.floats(allow_nan=True, allow_infinity=True)
        ids = st.text(st.characters(min_codepoint=1, max_codepoint=0x10FFFF), max_size=30)
        alt = st.floats(ALT_MIN_M, ALT_MAX_M)  # a Position holds no other
        fix, sats, modes = st.integers(-1, 12), st.integers(-1, 300), st.integers(-1, 2**33)
        ew = st.sampled_from(["permissive", "active", "heavy", "off"])
    texts = st.text(chars, max_size=64 if sane else 80)
    names = st.text(chars, min_size=1, max_size=20)
    some = st.none() | number
    positions = st.builds(
        Position,
        lat_deg=st.floats(-90, 90),
        lon_deg=st.floats(-180, 180),
        alt_msl_m=st.none() | alt,
        alt_hae_m=st.none() | alt,
        alt_rel_home_m=st.none() | alt,
    )
    detections = st.builds(
        Detection,
        event_id=ids,
        airframe=names,
        time=times,
        sensor=st.sampled_from(list(Sensor)),
        object_class=texts,
        subtype=texts,
        confidence=st.floats(0, 1),
        position=positions,
        sigma_h_m=st.floats(0, 1e300),
        late_by_s=st.none() | st.floats(0, 1e6),
    )
    tracks = st.builds(
        Track,
        event_id=ids,
        track_id=names,
        time=times,
        status=st.sampled_from(["created", "updated", "lost"]),
        object_class=texts,
        subtype=texts,
        confidence=st.floats(0, 1),
        class_conflict=st.floats(0, 1),
        position=positions,
        cep50_m=st.floats(0, 1e6),
        cep90_m=st.floats(0, 1e6),
        speed_mps=st.none() | st.floats(0, 1e4),
        course_deg=st.none() | st.floats(0, 360, exclude_max=True),
        airframes=st.lists(names, max_size=5).map(tuple),
        sensors=st.lists(st.sampled_from(list(Sensor)), max_size=5).map(tuple),
        detection_count=st.integers(0, 10**6),
        first_seen=times,
        last_seen=times,
        hostility=st.sampled_from(["hostile", "suspect", "unknown", "neutral", "friend"]),
        sidc=st.none() | texts,
        late_by_s=st.none() | st.floats(0, 1e6),
    )
    telemetries = st.builds(
        Telemetry,
        event_id=ids,
        airframe=names,
        time=times,
        position=st.none() | positions,
        alt_agl_m=st.none() | alt,
        attitude=st.none() | st.builds(Attitude, roll_rad=number, pitch_rad=number, yaw_rad=number),
        velocity=st.none()
        | st.builds(Velocity, north_mps=number, east_mps=number, down_mps=number),
        heading_deg=some,
        groundspeed_mps=some,
        airspeed_mps=some,
        climb_mps=some,
        gps_fix_type=st.none() | fix,
        satellites_visible=st.none() | sats,
        h_acc_m=st.none() | st.floats(0, 1e4),
        battery_pct=st.none() | st.floats(0, 100) if sane else some,
        battery_voltage_v=some,
        battery_current_a=some,
        battery_consumed_wh=some,
        battery_time_remaining_s=st.none() | st.floats(0, 1e6) if sane else some,
        endurance_remaining_min=st.none() | st.floats(0, 1e6),
        ew_mode=st.none() | ew,
        mav_type=st.none() | st.integers(0, 30),
        autopilot=st.none() | st.integers(0, 20),
        is_armed=st.none() | st.booleans(),
        custom_mode=st.none() | modes,
        system_status=st.none() | st.integers(-1, 12),
        active_link=st.none() | texts,
    )
    return detections | tracks | telemetries


times = st.datetimes(
    min_value=datetime(2000, 1, 1),  # noqa: DTZ001 - hypothesis takes naive bounds
    max_value=datetime(2100, 1, 1),  # noqa: DTZ001 - the zone comes from timezones=
    timezones=st.sampled_from([UTC, timezone(timedelta(hours=2))]),
)


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(event=event_strategies(sane=True))
def test_every_event_as_ingest_makes_it_is_written_valid(event: Any) -> None:
    """Any detection, track or telemetry with values the schema holds: every document valid."""
    documents = encode_event(event)
    expected = 1
    if isinstance(event, Telemetry):
        expected = 2 if event.position is not None else 1
    assert len(documents) == expected
    for document in documents:
        root = valid(document.payload)
        assert root.get("id") == document.doc_id
        assert document.event_id == event.event_id


@settings(
    max_examples=fuzz_examples(300), deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(event=event_strategies(sane=False))
def test_any_event_is_written_valid_or_refused_by_name(event: Any) -> None:
    """Anything the models allow: every document passes the XSD, or ValueError says why."""
    try:
        documents = encode_event(event)
    except ValueError as exc:
        refused = str(exc)
    else:
        refused = ""
    if refused:
        assert refused.startswith(f"{event.kind} ")  # names the event, then the field
        return
    for document in documents:
        valid(document.payload)


class TestOrders:
    """Orders documents in: every field read, every problem named by its element."""

    def test_a_full_order_is_read_exactly(self) -> None:
        payload = order_document(
            "doc-17",
            "ORD-42",
            issuer="2 brig S3",
            airframe="F26E-001",
            task="track_target",
            mgrs="34W DA 12345 67890",
            not_before="2026-11-22T12:05:00Z",
            not_after="2026-11-22T14:00:00+01:00",
            target="T-72 column",
            track_id="T-7",
            priority="immediate",
            reporting="every 5 min",
            measures=["stay east of PL BLUE", "min 300 m AGL"],
        )
        assert schema_accepts(payload)
        parsed = parse_document(payload, source="brigade")
        assert isinstance(parsed, OrderDocument)
        assert parsed.doc_id == "doc-17"
        order = parsed.order
        assert (order.event_id, order.order_id, order.source) == (
            "sweccis-order-ORD-42",
            "ORD-42",
            "brigade",
        )
        assert order.task is OrderTask.TRACK_TARGET
        assert order.priority is OrderPriority.IMMEDIATE
        ref = from_mgrs("34WDA1234567890")
        assert order.location.point is not None
        assert (order.location.point.lat_deg, order.location.point.lon_deg) == (
            ref.lat_deg,
            ref.lon_deg,
        )
        assert order.location.mgrs == "34W DA 12345 67890"
        assert order.not_before == datetime(2026, 11, 22, 12, 5, tzinfo=UTC)
        assert order.not_after == datetime(2026, 11, 22, 13, 0, tzinfo=UTC)
        assert (order.target, order.track_id) == ("T-72 column", "T-7")
        assert order.control_measures == ("stay east of PL BLUE", "min 300 m AGL")
        assert (order.issuer, order.airframe, order.reporting) == (
            "2 brig S3",
            "F26E-001",
            "every 5 min",
        )

    def test_a_minimal_point_order_and_a_polygon_order(self) -> None:
        point = parse_document(order_document("d1", "O1"), source="s")
        assert isinstance(point, OrderDocument)
        assert point.order.priority is OrderPriority.ROUTINE
        assert point.order.location.point == Position(lat_deg=65.8252, lon_deg=21.6886)
        corners = [(65.0, 21.0), (65.1, 21.0), (65.1, 21.2)]
        payload = order_document("d2", "O2", task="recon_area", polygon=corners)
        assert schema_accepts(payload)
        area = parse_document(payload, source="s")
        assert isinstance(area, OrderDocument)
        assert [(p.lat_deg, p.lon_deg) for p in area.order.location.polygon] == corners

    @pytest.mark.parametrize(
        ("change", "element", "schema_catches"),
        [
            ((b"<Task>observe_point", b"<Task>strike"), "FiveLineOrder/Task", True),
            ((b'latDeg="65.8252"', b'latDeg="95"'), "Location/Point/@latDeg", True),
            ((b'latDeg="65.8252"', b'latDeg="NaN"'), "Location/Point/@latDeg", True),
            ((b'lonDeg="21.6886"', b""), "Location/Point/@lonDeg", True),
            ((b"<Time>2026-11-22T12:00:00Z", b"<Time>2026-11-22T12:00:00"), "Time", True),
            ((b"<OrderId>O1</OrderId>", b""), "FiveLineOrder", True),
            ((b"<OrderId>O1", b"<OrderId>O1<Extra/>"), "OrderId", True),
            ((b"<Task>", b"<Bogus/><Task>"), "FiveLineOrder", True),
            ((b"<FiveLineOrder>", b'<FiveLineOrder x="1">'), "FiveLineOrder/@x", True),
            ((b'version="1"', b'version="2"'), "Orders/@version", True),
            ((b'id="d1"', b'id="has space"'), "Orders/@id", True),
        ],
    )
    def test_a_bad_field_is_named_and_the_schema_agrees(
        self, change: tuple[bytes, bytes], element: str, schema_catches: bool
    ) -> None:
        payload = order_document("d1", "O1").replace(*change)
        assert payload != order_document("d1", "O1")
        with pytest.raises(DocumentError) as caught:
            parse_document(payload, source="s")
        assert element in caught.value.element
        assert schema_accepts(payload) is not schema_catches

    @pytest.mark.parametrize(
        ("fields", "element", "schema_catches"),
        [
            ({"mgrs": "34W DA 12345 6789"}, "Location/Mgrs", True),
            ({"mgrs": "ZAA 12345 67890"}, "Location/Mgrs", True),  # polar UPS
            ({"mgrs": "34W IA 12345 67890"}, "Location/Mgrs", True),  # no column letter I
            ({"polygon": [(65, 21), (65.1, 21)]}, "Location/Polygon", True),
            (
                {"not_before": "2026-11-22T13:00:00Z", "not_after": "2026-11-22T12:00:00Z"},
                "Window",
                False,
            ),  # the XSD cannot compare two attributes: ours is the only check
            ({"priority": "urgent"}, "Priority", True),
            ({"measures": ["x" * 257]}, "ControlMeasures/Measure", True),
            ({"measures": [str(i) for i in range(17)]}, "ControlMeasures", True),
            ({"airframe": "A" * 65}, "Airframe", True),
            ({"track_id": ""}, "Target/@trackId", True),
        ],
    )
    def test_a_bad_order_carries_its_document_id(
        self, fields: dict[str, Any], element: str, schema_catches: bool
    ) -> None:
        payload = order_document("doc-9", "O9", **fields)
        with pytest.raises(DocumentError) as caught:
            parse_document(payload, source="s")
        assert element in caught.value.element, caught.value
        assert caught.value.doc_id == "doc-9"
        assert schema_accepts(payload) is not schema_catches

    @pytest.mark.parametrize(
        "payload",
        [
            b"",
            b"not xml",
            b'<!DOCTYPE x [<!ENTITY a "b">]><Ack/>',
            b'<Ack xmlns="urn:other" version="1" ref="a" status="accepted"/>',
            f'<?xml version="1.0" encoding="UTF-16"?><Ack xmlns="{NAMESPACE}"/>'.encode(),
            f'<Intel xmlns="{NAMESPACE}" version="1" id="x"/>'.encode(),
            f'<Ack xmlns="{NAMESPACE}" version="1" ref="a" status="maybe"/>'.encode(),
            f'<Registered xmlns="{NAMESPACE}" version="1" ref="r"><Publish>Chat</Publish>'
            "</Registered>".encode(),
            b"<a>" * 40_000,
        ],
        ids=lambda p: p[:30].decode(errors="replace"),
    )
    def test_what_is_not_a_document_for_us_is_a_document_error(self, payload: bytes) -> None:
        with pytest.raises(DocumentError):
            parse_document(payload, source="s", max_bytes=100_000)

    def test_a_document_over_the_bound_is_refused_before_parsing(self) -> None:
        large = order_document("d", "O", reporting="x" * 500) * 20
        with pytest.raises(DocumentError, match="more than 4096"):
            parse_document(large, source="s", max_bytes=4096)

    def test_control_documents_are_read(self) -> None:
        registered = parse_document(
            f'<Registered xmlns="{NAMESPACE}" version="1" ref="r-1"><Publish>Intel</Publish>'
            "<Subscribe>Orders</Subscribe></Registered>".encode(),
            source="s",
        )
        assert registered == Registered("r-1", frozenset({Fas.INTEL}), frozenset({Fas.ORDERS}))
        ack = parse_document(encode_ack("d-1", "rejected", "schema"), source="s")
        assert ack == Ack("d-1", "rejected", "schema")

    @settings(max_examples=fuzz_examples(300), deadline=None)
    @given(data=st.binary(max_size=400))
    def test_arbitrary_bytes_are_a_document_or_a_document_error(self, data: bytes) -> None:
        with contextlib.suppress(DocumentError):
            parse_document(data, source="s")

    @settings(max_examples=fuzz_examples(300), deadline=None)
    @given(
        position=st.integers(0, 10_000),
        replacement=st.binary(min_size=0, max_size=4),
        width=st.integers(0, 4),
    )
    def test_a_damaged_order_is_an_order_or_a_document_error(
        self, position: int, replacement: bytes, width: int
    ) -> None:
        original = order_document("d", "O", mgrs="34W DA 12345 67890", measures=["a"])
        at = position % len(original)
        damaged = original[:at] + replacement + original[at + width :]
        try:
            parsed = parse_document(damaged, source="s")
        except DocumentError:
            return
        assert isinstance(parsed, OrderDocument | Ack | Registered)


def test_the_examples_in_the_documentation_are_valid() -> None:
    """Every XML example in docs/sweccis.md passes the shipped XSD of its own version."""
    doc = (ROOT / "docs" / "sweccis.md").read_text()
    examples = re.findall(r"```xml\n(.*?)```", doc, flags=re.DOTALL)
    assert len(examples) >= 7
    versions = []
    for example in examples:
        root = etree.fromstring(example.encode())
        schema = SCHEMA_2 if root.get("version") == "2" else SCHEMA
        assert schema.validate(root), (example, schema.error_log)
        versions.append(root.get("version"))
    assert "2" in versions
