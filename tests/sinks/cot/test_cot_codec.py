"""CoT encodings checked by independent oracles: the MITRE schema, takproto, our validator."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import TypeAdapter
from test_cot_event import EVENTS, T0, options

from gateway.events import Detection, Position, Sensor, Telemetry, Track, Velocity
from gateway.testing import fuzz_examples
from sinks.cot.codec import Encoded, cot_time, decimal, to_proto, to_xml
from sinks.cot.event import CotEvent, build
from sinks.cot.proto import mesh_frame, stream_frame
from sinks.cot.validate import parse_cot

takproto = pytest.importorskip("takproto")
etree = pytest.importorskip("lxml.etree")

CORPUS = Path(__file__).resolve().parents[3].parent / "shared" / "corpus" / "cot"
EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
XSD = CORPUS / "atak_civ_takcot" / "mitre" / "CoT Base-Event Schema  (PUBLIC RELEASE).xsd"


def cot_events() -> list[CotEvent]:
    built = [build(e, options()) for e in EVENTS]
    return [e for e in built if e is not None]


def schema() -> etree.XMLSchema:
    if not XSD.exists():
        pytest.skip("shared corpus absent: no MITRE schema")
    return etree.XMLSchema(etree.parse(str(XSD)))


finite = st.floats(allow_nan=False, allow_infinity=False)
positions = st.builds(
    Position,
    lat_deg=st.floats(-90, 90).filter(lambda v: abs(v) > 1e-6),
    lon_deg=st.floats(-180, 180),
    alt_msl_m=st.none() | st.floats(-400, 20_000),
    alt_hae_m=st.none() | st.floats(-400, 20_000),
)
velocities = st.none() | st.builds(
    Velocity, north_mps=st.floats(-300, 300), east_mps=st.floats(-300, 300), down_mps=finite
)
times = st.datetimes(
    min_value=datetime(2000, 1, 1),  # noqa: DTZ001 - hypothesis takes naive bounds ...
    max_value=datetime(2100, 1, 1),  # noqa: DTZ001 - ... and adds the zone from timezones=
    timezones=st.just(UTC),
)
text = st.text(max_size=20)
telemetry = st.builds(
    Telemetry, event_id=st.just("t"), airframe=text.filter(str.strip), time=times,
    position=positions, velocity=velocities, battery_pct=st.none() | st.floats(0, 100),
    h_acc_m=st.none() | st.floats(0, 1e4), mav_type=st.none() | st.integers(0, 50),
    heading_deg=st.none() | st.floats(0, 360), groundspeed_mps=st.none() | st.floats(0, 300),
    active_link=st.none() | text, ew_mode=st.none() | text,
)  # fmt: skip
detections = st.builds(
    Detection, event_id=text.filter(str.strip), airframe=text, time=times,
    sensor=st.sampled_from(Sensor), object_class=st.sampled_from(["tank", "uav", "zz", "a<b"]),
    subtype=text, confidence=st.floats(0, 1), position=positions, sigma_h_m=st.floats(0, 1e4),
)  # fmt: skip
tracks = st.builds(
    Track, event_id=st.just("k"), track_id=text.filter(str.strip), time=times,
    object_class=st.sampled_from(["armour", "loitering_munition", "x&y"]), subtype=text,
    confidence=st.floats(0, 1), position=positions, cep50_m=st.floats(0, 1e4),
    cep90_m=st.floats(0, 1e4), velocity=velocities, airframes=st.lists(text, max_size=3).map(tuple),
    first_seen=times, last_seen=times,
    hostility=st.sampled_from(["hostile", "suspect", "unknown", "neutral", "friend"]),
)  # fmt: skip


class TestXml:
    """XML as TAK servers and ATAK expect it, and as the MITRE schema requires."""

    @pytest.mark.parametrize("index", range(3))
    def test_validates_against_the_mitre_schema(self, index: int) -> None:
        xsd = schema()
        data = to_xml(cot_events()[index])
        assert xsd.validate(etree.fromstring(data)), xsd.error_log
        assert parse_cot(data, strict=True).uid == cot_events()[index].uid

    @settings(max_examples=fuzz_examples(150), deadline=None)
    @given(event=telemetry | detections | tracks)
    def test_every_event_we_can_emit_is_valid(self, event: Telemetry | Detection | Track) -> None:
        """Whatever the event holds: schema-valid, strictly valid, and takproto reads it."""
        xsd = schema()
        cot = build(event, options())
        assert cot is not None
        data = to_xml(cot)
        assert xsd.validate(etree.fromstring(data)), xsd.error_log
        parsed = parse_cot(data, strict=True)
        assert (parsed.uid, parsed.type) == (cot.uid, cot.type)
        assert parsed.lat == pytest.approx(cot.lat, abs=1e-9)
        message = takproto.parse_proto(bytearray(data))
        assert message.cotEvent.uid == cot.uid

    def test_declaration_newline_event_and_nothing_after(self) -> None:
        data = to_xml(cot_events()[0])
        assert data.startswith(b'<?xml version="1.0" encoding="UTF-8" standalone="yes"?>\n<event ')
        assert data.endswith(b"</event>")
        assert data.count(b"\n") == 1

    def test_times_are_utc_milliseconds(self) -> None:
        event = cot_events()[0]
        later = datetime(2026, 11, 22, 11, 15, 30, 250999, tzinfo=UTC).astimezone()
        data = to_xml(CotEvent(**{**_fields(event), "time": later}))
        assert b'time="2026-11-22T11:15:30.250Z"' in data

    @pytest.mark.parametrize(
        ("value", "places", "text"),
        [
            (1e-05, 9, "0.00001"),
            (9999999.0, 2, "9999999.0"),
            (-0.0, 2, "-0.0"),
            (12.3456, 2, "12.35"),
        ],
    )
    def test_decimals_have_no_exponent(self, value: float, places: int, text: str) -> None:
        assert decimal(value, places) == text

    def test_takproto_reads_the_detail_fields(self) -> None:
        message = takproto.parse_proto(bytearray(to_xml(cot_events()[0])))
        detail = message.cotEvent.detail
        assert detail.track.speed == pytest.approx(23.02, abs=0.01)
        assert detail.status.battery == 76
        assert detail.contact.callsign == "FISCHER F26E-007"


def _fields(event: CotEvent) -> dict[str, object]:
    return {name: getattr(event, name) for name in CotEvent.__slots__}


class TestProtobuf:
    """TAK protocol v1: takproto decodes both framings to the same event."""

    @pytest.mark.parametrize("index", range(3))
    def test_takproto_decodes_mesh_and_stream(self, index: int) -> None:
        event = cot_events()[index]
        for framed in (mesh_frame(to_proto(event)), stream_frame(to_proto(event))):
            cot = takproto.parse_proto(bytearray(framed)).cotEvent
            assert (cot.uid, cot.type, cot.how) == (event.uid, event.type, event.how)
            assert (cot.lat, cot.lon, cot.hae, cot.ce) == (
                event.lat,
                event.lon,
                event.hae,
                event.ce,
            )
            assert cot.sendTime == int(event.time.timestamp() * 1000)
            assert cot.staleTime == int(event.stale.timestamp() * 1000)
            assert cot.detail.contact.callsign == event.callsign
            assert cot.detail.xmlDetail == event.xml_detail

    @settings(max_examples=fuzz_examples(150), deadline=None)
    @given(event=telemetry | detections | tracks)
    def test_our_encoding_agrees_with_takproto(self, event: Telemetry | Detection | Track) -> None:
        """takproto's own XML→protobuf encoding of our XML decodes to what ours decodes to."""
        cot = build(event, options())
        assert cot is not None
        ours = takproto.parse_proto(bytearray(mesh_frame(to_proto(cot)))).cotEvent
        theirs = takproto.parse_proto(bytearray(to_xml(cot))).cotEvent
        assert (ours.uid, ours.type, ours.how) == (theirs.uid, theirs.type, theirs.how)
        # takproto turns the XML time into ms through a float and can land 1 ms low.
        assert abs(ours.sendTime - theirs.sendTime) <= 1
        assert abs(ours.staleTime - theirs.staleTime) <= 1
        parsed = parse_cot(to_xml(cot))
        assert ours.sendTime == (parsed.time - EPOCH) // timedelta(milliseconds=1)
        assert ours.lat == pytest.approx(theirs.lat, abs=1e-9)
        assert ours.hae == pytest.approx(theirs.hae, abs=0.01)
        assert ours.detail.contact.callsign == theirs.detail.contact.callsign
        assert ours.detail.track.course == pytest.approx(theirs.detail.track.course, abs=0.01)
        assert parse_cot(mesh_frame(to_proto(cot))).uid == cot.uid

    def test_one_encoding_per_format(self) -> None:
        encoded = Encoded(cot_events()[1])
        assert encoded.get("mesh") is encoded.get("mesh")
        assert encoded.get("stream")[0] == 0xBF
        assert encoded.get("mesh")[3:] == encoded.get("stream")[-len(encoded.get("mesh")) + 3 :]

    def test_stale_after_start_survives_truncation(self) -> None:
        event = cot_events()[0]
        short = CotEvent(**{**_fields(event), "stale": event.start + timedelta(seconds=1)})
        assert parse_cot(to_xml(short), strict=True).stale > parse_cot(to_xml(short)).start
        assert event.time == T0


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(
    st.datetimes(
        min_value=datetime(1970, 1, 2),  # noqa: DTZ001 - hypothesis adds the zone
        max_value=datetime(2999, 12, 30),  # noqa: DTZ001
        timezones=st.sampled_from(
            [UTC, timezone(timedelta(hours=2)), timezone(timedelta(minutes=-330))]
        ),
    ),
    st.booleans(),
)
def test_a_cot_time_is_utc_with_milliseconds_cut_not_rounded(value: datetime, read: bool) -> None:
    if read:  # as read back from the spool: pydantic's own UTC tzinfo
        value = TypeAdapter(datetime).validate_json(f'"{value.isoformat()}"')
    utc = value.astimezone(UTC)
    expected = utc.strftime("%Y-%m-%dT%H:%M:%S.") + f"{utc.microsecond // 1000:03d}Z"
    assert cot_time(value) == expected
