"""The NFFI 1.3 codec: documents valid against the NFFI 1.3 XSD, read back, and hostile input.

The XSD is NATO's ``nffi_13.xsd`` as republished in the shared corpus (its licence forbids
shipping it, so it is read from there and the schema tests skip without it). lxml is the
independent validator; our parser reads back what we wrote (hypothesis), and arbitrary bytes
give tracks or ``NffiError``, never another exception.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from lxml import etree

from gateway.errors import FrameError
from gateway.events import BlueForce, Position, Telemetry, Velocity
from gateway.testing import fuzz_examples
from sinks.nffi.codec import (
    KMH_PER_MPS,
    MAX_TRACKS,
    NffiError,
    NffiOptions,
    ParsedMessage,
    encode_message,
    encode_track,
    fit_identifier,
    parse_message,
    tracks_of,
)
from sinks.nffi.stream import MessageSplitter

PROBLEMS = {"oversize", "dtd", "xml", "root"}
XSD_NAME = "nffi/nffi13_sip3/SIP3_Service_ReqRes.xsd_1.xsd"
T0 = datetime(2026, 11, 22, 10, 15, 30, 250_000, tzinfo=UTC)
OPTS = NffiOptions(
    system="FISCHER-GW", country="SWE", sec_policy_name="NATO", sec_classification="UNCLASSIFIED"
)


def corpus_file(name: str) -> Path | None:
    for root in (Path(__file__).resolve().parents[3] / ".." / "shared" / "corpus",):
        if (root / name).is_file():
            return root / name
    return None


@pytest.fixture(scope="module")
def corpus_xsd() -> etree.XMLSchema | None:
    """The NFFI 1.3 XSD from the corpus, or None where it is absent."""
    path = corpus_file(XSD_NAME)
    return None if path is None else etree.XMLSchema(etree.parse(str(path)))


@pytest.fixture(scope="module")
def xsd(corpus_xsd: etree.XMLSchema | None) -> etree.XMLSchema:
    if corpus_xsd is None:
        pytest.skip(f"the NFFI 1.3 XSD ({XSD_NAME}) is not in shared/corpus")
    return corpus_xsd


def parse_or_problem(data: bytes, max_bytes: int = 1 << 20) -> ParsedMessage | str:
    """The message, or the problem code of the ``NffiError`` (any other exception escapes)."""
    try:
        return parse_message(data, max_bytes=max_bytes)
    except NffiError as exc:
        return exc.problem


def validate(xsd: etree.XMLSchema, document: bytes) -> None:
    root = etree.fromstring(document)
    assert xsd.validate(root), str(xsd.error_log)


def telemetry(**changes: object) -> Telemetry:
    values: dict[str, object] = {
        "event_id": "t-1",
        "airframe": "F26E-001",
        "time": T0,
        "position": Position(lat_deg=58.410812, lon_deg=15.621403, alt_msl_m=612.4),
        "velocity": Velocity(north_mps=0.0, east_mps=25.0, down_mps=0.0),
        "mav_type": 1,
    }
    return Telemetry.model_validate(values | changes)


def blue(**changes: object) -> BlueForce:
    values: dict[str, object] = {
        "event_id": "b-1",
        "uid": "ANDROID-1234",
        "time": T0,
        "callsign": "3 PLUT",
        "position": Position(lat_deg=58.415, lon_deg=15.64),
        "source": "cot",
    }
    return BlueForce.model_validate(values | changes)


class TestEncoding:
    def test_own_airframe_track_is_schema_valid_and_complete(self, xsd: etree.XMLSchema) -> None:
        document = encode_message(tracks_of([telemetry()], OPTS))
        validate(xsd, document)
        ((track,),) = [parse_message(document).tracks]
        assert (track.country, track.system, track.transponder_id) == (
            "SWE",
            "FISCHER-GW",
            "F26E-001",
        )
        assert track.time == T0.replace(microsecond=0)
        assert (track.lat_deg, track.lon_deg, track.alt_msl_m) == (58.410812, 15.621403, 612.4)
        assert track.bearing_deg == 90.0
        assert track.unit_symbol == "SFAPMFQ--------"  # a friendly fixed-wing UAV

    def test_speed_is_written_in_kmh_and_read_back_in_mps(self) -> None:
        document = encode_message(tracks_of([telemetry()], OPTS))
        assert b"<speed>90</speed>" in document  # 25 m/s
        assert parse_message(document).tracks[0].speed_mps == pytest.approx(25.0)
        assert KMH_PER_MPS == 3.6

    def test_groundspeed_and_heading_when_there_is_no_velocity(self) -> None:
        event = telemetry(velocity=None, heading_deg=359.99999, groundspeed_mps=10.0)
        track = parse_message(encode_message(tracks_of([event], OPTS))).tracks[0]
        assert track.bearing_deg == 0.0  # never 360: the schema's bearing is < 360
        assert track.speed_mps == pytest.approx(10.0)

    def test_a_longitude_that_rounds_to_minus_180_is_written_180(
        self, xsd: etree.XMLSchema
    ) -> None:
        """Found by hypothesis: -179.99999999 printed with 7 decimals is -180, out of range."""
        event = telemetry(position=Position(lat_deg=1.0, lon_deg=-179.99999999))
        document = encode_message(tracks_of([event], OPTS))
        validate(xsd, document)
        assert parse_message(document).tracks[0].lon_deg == 180.0

    def test_relayed_friend_with_odd_names_is_schema_valid(self, xsd: etree.XMLSchema) -> None:
        event = blue(
            uid="ANDROID abc/def " + "x" * 80,
            callsign="Pluton Åsa-Öster 3",
            position=Position(lat_deg=-90.0, lon_deg=-180.0, alt_hae_m=95.0),
            speed_mps=2.0,
            course_deg=271.5,
            sidc="SFGPUCI----D---",
        )
        opts = NffiOptions(subsystem="relay", geoid=lambda lat, lon: 30.0)
        document = encode_message(tracks_of([event], opts))
        validate(xsd, document)
        track = parse_message(document).tracks[0]
        assert len(track.transponder_id) == 60
        assert track.unit_short_name == "Pluton-Asa-Oste"  # accents dropped, 15 characters
        assert track.lon_deg == 180.0  # the schema's longitude excludes -180
        assert track.alt_msl_m == 65.0  # hae 95 minus the geoid's 30
        assert track.speed_mps == pytest.approx(2.0)
        assert track.unit_symbol == "SFGPUCI----D---"

    def test_an_empty_message_is_a_valid_heartbeat(self, xsd: etree.XMLSchema) -> None:
        validate(xsd, encode_message([]))
        assert parse_message(encode_message([])).tracks == ()

    def test_no_position_or_null_island_is_no_track(self) -> None:
        assert encode_track(telemetry(position=None), OPTS) is None
        assert encode_track(blue(position=Position(lat_deg=0.0, lon_deg=0.0)), OPTS) is None

    @settings(max_examples=fuzz_examples(100), deadline=None)
    @given(st.text(max_size=120), st.integers(min_value=1, max_value=60))
    def test_identifiers_always_fit_the_schema_alphabet(self, text: str, size: int) -> None:
        fitted = fit_identifier(text, size)
        assert 1 <= len(fitted) <= size
        assert all(c.isascii() and (c.isalnum() or c in ".,:*-") for c in fitted)


positions = st.builds(
    Position,
    lat_deg=st.floats(-90, 90),
    lon_deg=st.floats(-180, 180),
    alt_msl_m=st.none() | st.floats(-400, 30_000),
).filter(lambda p: abs(p.lat_deg) > 1e-3 or abs(p.lon_deg) > 1e-3)


@settings(
    max_examples=fuzz_examples(150),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    position=positions,
    airframe=st.text(min_size=1, max_size=40),
    north=st.floats(-400, 400),
    east=st.floats(-400, 400),
    seconds=st.integers(0, 10**9),
)
def test_any_telemetry_encodes_valid_and_reads_back(
    corpus_xsd: etree.XMLSchema | None,
    position: Position,
    airframe: str,
    north: float,
    east: float,
    seconds: int,
) -> None:
    time = datetime(2000, 1, 1, tzinfo=UTC) + timedelta(seconds=seconds)
    event = telemetry(
        airframe=airframe,
        time=time,
        position=position,
        velocity=Velocity(north_mps=north, east_mps=east, down_mps=0.0),
    )
    document = encode_message(tracks_of([event], OPTS))
    if corpus_xsd is not None:  # without the corpus: read back by our parser's checks only
        validate(corpus_xsd, document)
    (track,) = parse_message(document).tracks
    assert track.time == time
    assert track.lat_deg == pytest.approx(position.lat_deg, abs=1e-7)
    if track.lon_deg == 180.0 and position.lon_deg < 0:
        assert position.lon_deg <= -180.0 + 5e-8  # written as 180: the same meridian
    else:
        assert track.lon_deg == pytest.approx(position.lon_deg, abs=1e-7)
    if position.alt_msl_m is not None:
        assert track.alt_msl_m == pytest.approx(position.alt_msl_m, abs=1e-6)
    assert track.speed_mps == pytest.approx(math.hypot(north, east), abs=1e-3)
    assert track.transponder_id == fit_identifier(airframe, 60)


class TestParsing:
    def wrap(self, body: str, root: str = "NFFIMessage") -> bytes:
        return f'<{root} xmlns="urn:nato:fft:protocols:nffi13">{body}</{root}>'.encode()

    def test_refuses_dtds_and_entities(self) -> None:
        bomb = (
            b'<?xml version="1.0"?><!DOCTYPE x [<!ENTITY a "aaaa">]><NFFIMessage>&a;</NFFIMessage>'
        )
        with pytest.raises(NffiError) as caught:
            parse_message(bomb)
        assert caught.value.problem == "dtd"

    def test_other_roots_and_broken_xml_are_errors_with_a_problem(self) -> None:
        for data, problem in [
            (self.wrap("", root="event"), "root"),
            (b"<NFFIMessage xmlns='urn:other'/>", "root"),
            (b"<NFFIMessage><track>", "xml"),
            (b"x" * 2000, "oversize"),
        ]:
            with pytest.raises(NffiError) as caught:
                parse_message(data, max_bytes=1024)
            assert caught.value.problem == problem
            assert isinstance(caught.value, FrameError)

    def test_a_bad_track_is_skipped_and_the_good_one_kept(self) -> None:
        good = tracks_of([telemetry()], OPTS)[0]
        bad_time = good.replace("<dateTime>20261122101530</dateTime>", "<dateTime>2026</dateTime>")
        bad_lat = good.replace("<latitude>58.410812</latitude>", "<latitude>NaN</latitude>")
        no_source = "<track><positionalData/></track>"
        message = parse_message(self.wrap(bad_time + bad_lat + no_source + good))
        assert len(message.tracks) == 1
        assert message.skipped == ("dateTime", "latitude", "trackSource")

    def test_at_most_max_tracks_are_read(self) -> None:
        good = tracks_of([telemetry()], OPTS)[0]
        message = parse_message(self.wrap(good * (MAX_TRACKS + 5)), max_bytes=10**7)
        assert len(message.tracks) == MAX_TRACKS
        assert message.skipped == ("too_many_tracks",)

    def test_a_prefixed_nffi14_document_is_read(self) -> None:
        good = tracks_of([telemetry()], OPTS)[0].replace("<", "<n:").replace("<n:/", "</n:")
        data = f'<n:NFFIMessage xmlns:n="urn:nato:fft:protocols:nffi14">{good}</n:NFFIMessage>'
        assert len(parse_message(data.encode()).tracks) == 1

    @settings(max_examples=fuzz_examples(400), deadline=None)
    @given(st.binary(max_size=2048))
    def test_arbitrary_bytes_are_tracks_or_an_nffi_error(self, data: bytes) -> None:
        outcome = parse_or_problem(data, max_bytes=1024)
        assert outcome in PROBLEMS or isinstance(outcome, ParsedMessage)

    @settings(max_examples=fuzz_examples(300), deadline=None)
    @given(st.lists(st.tuples(st.integers(0, 10**6), st.binary(max_size=4)), max_size=6))
    def test_a_mangled_valid_document_is_tracks_or_an_nffi_error(
        self, edits: list[tuple[int, bytes]]
    ) -> None:
        """Bytes near a valid document reach the track checks, which arbitrary bytes rarely do."""
        data = bytearray(
            encode_message(tracks_of([telemetry(), blue(sidc="SHGPUCI--------")], OPTS))
        )
        for where, replacement in edits:
            at = where % len(data)
            data[at : at + len(replacement)] = replacement
        outcome = parse_or_problem(bytes(data))
        if isinstance(outcome, ParsedMessage):
            assert len(outcome.tracks) + len(outcome.skipped) <= 2
        else:
            assert outcome in PROBLEMS


class TestFraming:
    def test_documents_back_to_back_in_any_chunks_after_a_stray_fragment(self) -> None:
        document = encode_message(tracks_of([telemetry()], OPTS))
        heartbeat = b'<n:NFFIMessage xmlns:n="urn:nato:fft:protocols:nffi13"\n/>'
        stream = b"</track>  " + document + heartbeat + document.strip()
        for size in (1, 7, 64, len(stream)):
            splitter = MessageSplitter(4096)
            out: list[bytes] = []
            for i in range(0, len(stream), size):
                out += splitter.feed(stream[i : i + size])
            assert out == [document.rstrip(b"\n"), heartbeat, document.strip()]
            assert splitter.fragments == 1
            assert splitter.buffered == 0

    def test_a_stream_without_an_end_overflows(self) -> None:
        splitter = MessageSplitter(1024)
        assert splitter.feed(b"<NFFIMessage>" + b"<track>" * 200) == []
        assert splitter.is_overflowing

    @settings(max_examples=fuzz_examples(300), deadline=None)
    @given(st.lists(st.binary(max_size=600), max_size=8), st.sampled_from([b"", b"</NFFIMessage>"]))
    def test_arbitrary_streams_split_and_parse_without_surprises(
        self, chunks: list[bytes], tail: bytes
    ) -> None:
        splitter = MessageSplitter(2048)
        for chunk in [*chunks, tail]:
            for document in splitter.feed(chunk):
                assert document.rstrip().endswith(b">")
                outcome = parse_or_problem(document, max_bytes=2048)
                assert outcome in PROBLEMS or isinstance(outcome, ParsedMessage)
            if splitter.is_overflowing:
                break
        assert splitter.buffered <= 2048 + 600 + len(tail)
