"""Gateway events to CoT: types and symbols, uids, times, hae from the geoid, ce, detail."""

from __future__ import annotations

import struct
from datetime import UTC, datetime, timedelta
from pathlib import Path
from xml.sax.saxutils import quoteattr

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.domain.geoid import GeoidGrid, bundled_geoid
from gateway.domain.symbols import cot_type_from_sidc, object_symbol, own_symbol
from gateway.events import (
    MAX_TRACK_NODES,
    BlueForce,
    Detection,
    LinkState,
    Position,
    Sensor,
    Telemetry,
    Track,
    Velocity,
)
from gateway.testing import fuzz_examples
from sinks.cot.codec import to_proto, to_xml
from sinks.cot.event import CotOptions, StaleTimes, build, xml_attribute, xml_safe
from sinks.cot.proto import mesh_frame
from sinks.cot.validate import UNKNOWN

T0 = datetime(2026, 11, 22, 10, 15, 30, 250000, tzinfo=UTC)
DATA = Path(__file__).resolve().parents[3] / "gateway" / "data"
EGM96_15 = Path("/usr/share/proj/egm96_15.gtx")

TELEMETRY = Telemetry(
    event_id="t1",
    airframe="F26E-007",
    time=T0,
    position=Position(lat_deg=58.4108123, lon_deg=15.6214031, alt_msl_m=583.0, alt_hae_m=612.4),
    velocity=Velocity(north_mps=1.0, east_mps=23.0, down_mps=0.0),
    heading_deg=80.0,
    groundspeed_mps=23.0,
    battery_pct=76.4,
    h_acc_m=4.5,
    gps_fix_type=3,
    mav_type=1,
    active_link="sdr",
)
DETECTION = Detection(
    event_id="d1",
    airframe="F26E-007",
    time=T0,
    sensor=Sensor.IR,
    object_class="tank",
    subtype="T-72",
    confidence=0.91,
    position=Position(lat_deg=58.423917, lon_deg=15.650112, alt_msl_m=120.0),
    sigma_h_m=12.0,
)
TRACK = Track(
    event_id="k1",
    track_id="2026-000042",
    time=T0,
    object_class="uav",
    confidence=0.78,
    position=Position(lat_deg=58.401002, lon_deg=15.59877, alt_hae_m=245.0),
    cep50_m=20.0,
    cep90_m=36.5,
    velocity=Velocity(north_mps=10.0, east_mps=10.0, down_mps=0.0),
    detection_ids=("d1", "d2"),
    airframes=("F26E-007",),
    first_seen=T0,
    last_seen=T0,
    hostility="hostile",
)
EVENTS = (TELEMETRY, DETECTION, TRACK)


def options(**changes: object) -> CotOptions:
    """Options with the shipped geoid, as the sink builds them."""
    base: dict[str, object] = {"geoid": bundled_geoid().undulation}
    return CotOptions(**{**base, **changes})  # type: ignore[arg-type]


class TestTypes:
    """Types and symbols come from the data tables."""

    @pytest.mark.parametrize(
        ("mav_type", "cot_type", "sidc_d"),
        [
            (1, "a-f-A-M-F-Q", "10030100001103000000"),
            (2, "a-f-A-M-H-Q", "10030100001104000000"),
            (21, "a-f-A-M-F-Q", "10030100001104000000"),  # VTOL: cruises as a plane
            (43, "a-f-A-M-H-Q", "10030100001104000000"),  # generic multirotor
            (7, "a-f-A-M-L", "10030100001105000000"),  # airship
            (8, "a-f-A-M-L", "10030100001105000000"),  # free balloon
            (10, "a-f-G-E-V", "10031500001200000000"),  # ground rover
            (11, "a-f-S", "10033000000000000000"),  # surface boat
            (12, "a-f-U", "10033500000000000000"),  # submarine (ArduSub)
            (None, "a-f-A-M-F-Q", "10030100001103000000"),  # no HEARTBEAT yet: the fleet's
            (0, "a-f-A", "10030100000000000000"),  # GENERIC: air, kind unknown
            (999, "a-f-A", "10030100000000000000"),
        ],
    )
    def test_own_airframe_type_follows_mav_type(
        self, mav_type: int | None, cot_type: str, sidc_d: str
    ) -> None:
        event = build(TELEMETRY.model_copy(update={"mav_type": mav_type}), options())
        assert event is not None
        assert event.type == cot_type
        assert f'sidc2525d="{sidc_d}"' in event.xml_detail

    def test_detection_and_track_types_and_codes(self) -> None:
        det, trk = build(DETECTION, options()), build(TRACK, options())
        assert det is not None
        assert trk is not None
        assert (det.type, det.how) == ("a-h-G-E-V-A-T", "m-i")
        assert 'sidc2525c="SHGPEVAT-------" sidc2525d="10061500001202000000"' in det.xml_detail
        assert (trk.type, trk.how) == ("a-h-A-M-F-Q", "m-f")

    @pytest.mark.parametrize(
        ("choice", "cot_type", "sidc_c"),
        [("uav_attack", "a-h-A-M-F-Q-A", "SHAPMFQA-------"), ("missile", "a-h-A-W-M", "SHAPWM---")],
    )
    def test_loitering_munition_symbol_is_configurable(
        self, choice: str, cot_type: str, sidc_c: str
    ) -> None:
        track = TRACK.model_copy(update={"object_class": "loitering_munition"})
        event = build(track, options(loitering_munition=choice))
        assert event is not None
        assert event.type == cot_type
        assert sidc_c in event.xml_detail

    def test_unknown_class_is_an_unspecified_ground_object_of_its_affiliation(self) -> None:
        track = TRACK.model_copy(update={"object_class": "class_9", "hostility": "suspect"})
        event = build(track, options())
        assert event is not None
        assert event.type == "a-s-G"
        assert 'sidc2525c="SSGP-----------" sidc2525d="10051000000000000000"' in event.xml_detail

    def test_a_merged_track_goes_stale_at_once_and_names_the_survivor(self) -> None:
        live = build(TRACK, options())
        merged = build(
            TRACK.model_copy(update={"status": "merged", "merged_into": "T9"}), options()
        )
        assert live is not None
        assert merged is not None
        assert merged.uid == live.uid
        assert merged.stale == TRACK.time + timedelta(seconds=1)
        assert live.stale > merged.stale
        assert "merged into T-T9" in merged.xml_detail

    def test_track_sidc_decides_the_type(self) -> None:
        event = build(TRACK.model_copy(update={"sidc": "SHGPUCA----D---"}), options())
        assert event is not None
        assert event.type == "a-h-G-U-C-A"
        assert "SHGPUCA----D---" in event.xml_detail

    @pytest.mark.parametrize(
        ("sidc", "cot_type"),
        [
            ("SHGPEVAT-------", "a-h-G-E-V-A-T"),
            ("SFGPUCI----D---", "a-f-G-U-C-I"),
            ("SUGP-----------", "a-u-G"),
            ("SDAPMFQ--------", "a-f-A-M-F-Q"),  # exercise friend
        ],
    )
    def test_sidc_to_cot_type(self, sidc: str, cot_type: str) -> None:
        assert cot_type_from_sidc(sidc) == cot_type

    def test_every_table_code_is_a_valid_symbol(self) -> None:
        """milsymbol accepts every code we can emit (letter codes with status as '-')."""
        milsymbol = pytest.importorskip("milsymbol")
        table = yaml.safe_load((DATA / "cot_types.yaml").read_text())
        symbols = [own_symbol(t) for g in table["own_airframes"].values() for t in g["mav_types"]]
        symbols.append(own_symbol(999))
        for hostility in ("hostile", "suspect", "unknown", "neutral", "friend"):
            for cls in ("tank", "armour", "uav", "infantry_platoon", "loitering_munition", "x"):
                for lm in ("uav_attack", "missile"):
                    symbols.append(object_symbol(cls, hostility, lm))  # type: ignore[arg-type]
        for symbol in symbols:
            letter = symbol.sidc_2525c[:3] + "-" + symbol.sidc_2525c[4:10]
            assert milsymbol.Symbol(letter).is_valid(), symbol
            assert milsymbol.Symbol(symbol.sidc_2525d).is_valid(), symbol
            assert cot_type_from_sidc(symbol.sidc_2525c) == symbol.cot_type


class TestPositionAndTimes:
    """Where and when: no position no event, hae never MSL, ce as 1σ, times from the event."""

    def test_no_position_no_event(self) -> None:
        assert build(Telemetry(event_id="x", airframe="A", time=T0), options()) is None

    @pytest.mark.parametrize("event", EVENTS, ids=["telemetry", "detection", "track"])
    def test_never_at_null_island(self, event: Telemetry | Detection | Track) -> None:
        assert (
            build(event.model_copy(update={"position": Position(lat_deg=0, lon_deg=0)}), options())
            is None
        )

    def test_other_kinds_have_no_cot(self) -> None:
        link = LinkState(
            event_id="l", airframe="A", time=T0, link="sdr", is_up=True, is_active=True,
            loss_pct=0.0, reason="up",
        )  # fmt: skip
        assert build(link, options()) is None

    def test_hae_prefers_the_ellipsoid_height(self) -> None:
        event = build(TELEMETRY, options())
        assert event is not None
        assert (event.hae, event.altsrc) == (612.4, "GPS")

    def test_msl_becomes_hae_through_the_geoid(self) -> None:
        msl_only = Position(lat_deg=58.4108, lon_deg=15.6214, alt_msl_m=583.0)
        event = build(TELEMETRY.model_copy(update={"position": msl_only}), options())
        detection = build(DETECTION, options())
        assert event is not None
        assert detection is not None
        assert event.hae == pytest.approx(583.0 + 29.4, abs=0.3)  # Linköping, N = 29.4 m
        assert event.altsrc == "CALC"
        assert detection.hae == pytest.approx(120.0 + 29.4, abs=0.3)

    def test_msl_is_never_sent_as_hae(self) -> None:
        msl_only = Position(lat_deg=58.4, lon_deg=15.6, alt_msl_m=583.0)
        event = build(TELEMETRY.model_copy(update={"position": msl_only}), CotOptions())
        assert event is not None
        assert (event.hae, event.altsrc) == (UNKNOWN, "???")

    def test_ce_is_one_sigma(self) -> None:
        own, det, trk = (build(e, options()) for e in EVENTS)
        assert own is not None
        assert det is not None
        assert trk is not None
        assert (own.ce, det.ce) == (4.5, 12.0)
        assert trk.ce == pytest.approx(20.0 / 1.1774, rel=1e-4)

    def test_times_come_from_the_event_and_stale_per_kind(self) -> None:
        opts = options(stale=StaleTimes(telemetry_s=5.0, detection_s=60.0, track_s=600.0))
        own, det, trk = (build(e, opts) for e in EVENTS)
        assert own is not None
        assert det is not None
        assert trk is not None
        assert own.time == own.start == T0
        assert [e.stale - T0 for e in (own, det, trk)] == [
            timedelta(seconds=5), timedelta(seconds=60), timedelta(seconds=600),
        ]  # fmt: skip

    def test_partial_stale_times_take_the_defaults_for_the_rest(self) -> None:
        """Issue 10: a partial stale table made every detection raise KeyError, forever."""
        opts = options(stale=StaleTimes(telemetry_s=10.0))
        own, det, trk = (build(e, opts) for e in EVENTS)
        assert own is not None
        assert det is not None
        assert trk is not None
        assert [e.stale - T0 for e in (own, det, trk)] == [
            timedelta(seconds=10), timedelta(seconds=120), timedelta(seconds=300),
        ]  # fmt: skip


class TestFixQuality:
    """``m-g`` and a GPS label only with a 3-D fix; an estimated position says so."""

    @pytest.mark.parametrize(
        ("fix_type", "how", "source"),
        [
            (0, "m-p", "ESTIMATED"),  # no GPS: the estimator dead-reckons
            (1, "m-p", "ESTIMATED"),  # GPS, no fix
            (2, "m-p", "ESTIMATED"),  # 2-D only: not trusted as GPS (cot.md section 5)
            (3, "m-g", "GPS"),
            (4, "m-g", "DGPS"),
            (6, "m-g", "RTK"),
            (7, "m-c", "USER"),  # static: a configured position
            (None, "m-g", "???"),  # no GPS_RAW_INT seen: no claim about the source
        ],
    )
    def test_how_and_geopointsrc_follow_the_fix_type(
        self, fix_type: int | None, how: str, source: str
    ) -> None:
        event = build(TELEMETRY.model_copy(update={"gps_fix_type": fix_type}), options())
        assert event is not None
        assert (event.how, event.geopointsrc) == (how, source)

    def test_no_fix_position_carries_no_gps_label_on_the_wire(self) -> None:
        position = Position(lat_deg=58.41, lon_deg=15.62, alt_msl_m=583.0)
        telemetry = TELEMETRY.model_copy(update={"gps_fix_type": 1, "position": position})
        event = build(telemetry, options())
        assert event is not None
        xml = to_xml(event)
        assert b'how="m-p"' in xml
        assert b"GPS" not in xml
        assert b'geopointsrc="ESTIMATED" altsrc="CALC"' in xml


class TestDetail:
    """Callsign, course and speed, remarks, links, battery."""

    def test_own_airframe_detail(self) -> None:
        event = build(TELEMETRY, options(group=("Cyan", "Team Member")))
        assert event is not None
        assert event.callsign == "FISCHER F26E-007"
        assert event.course_deg == pytest.approx(87.51, abs=0.01)  # over ground, not heading
        assert event.speed_mps == pytest.approx(23.02, abs=0.01)
        assert event.battery_pct == 76
        assert event.group == ("Cyan", "Team Member")
        assert '<uid Droid="FISCHER F26E-007"/>' in event.xml_detail

    def test_detection_remarks_and_link_to_the_reporting_airframe(self) -> None:
        own_types = {"F26E-007": "a-f-A-M-H-Q"}
        event = build(DETECTION, options(), own_types)
        assert event is not None
        assert "IR detection: tank T-72, confidence 0.91" in event.xml_detail
        assert (
            '<link uid="fischer-F26E-007" type="a-f-A-M-H-Q" relation="p-p"/>' in event.xml_detail
        )

    def test_telemetry_teaches_the_link_type(self) -> None:
        own_types: dict[str, str] = {}
        build(TELEMETRY.model_copy(update={"mav_type": 2}), options(), own_types)
        event = build(TRACK, options(), own_types)
        assert event is not None
        assert 'type="a-f-A-M-H-Q" relation="p-p"' in event.xml_detail
        assert "Fused track: uav, hostile, confidence 0.78, 2 detections" in event.xml_detail

    def test_course_is_below_360(self) -> None:
        north = Velocity(north_mps=10.0, east_mps=-1e-9, down_mps=0.0)
        event = build(TRACK.model_copy(update={"velocity": north}), options())
        assert event is not None
        assert event.course_deg is not None
        assert 0.0 <= event.course_deg < 360.0

    def test_uids_are_stable_and_without_whitespace(self) -> None:
        track = TRACK.model_copy(update={"track_id": "trk 42\t"})
        first, again = (
            build(track, options()),
            build(track.model_copy(update={"time": T0}), options()),
        )
        assert first is not None
        assert again is not None
        assert first.uid == again.uid == "fischer-trk-trk_42_"


class TestGeoid:
    """The shipped 30' EGM96 grid and PROJ's 15' grid agree with the known undulations."""

    @pytest.mark.parametrize(
        ("lat", "lon", "undulation_m"),
        [(55.605, 13.0038, 35.5), (58.4108, 15.6214, 29.4), (59.3293, 18.0686, 23.4),
         (67.8558, 20.2253, 30.0)],
    )  # fmt: skip
    def test_known_undulations(self, lat: float, lon: float, undulation_m: float) -> None:
        assert bundled_geoid().undulation(lat, lon) == pytest.approx(undulation_m, abs=0.5)
        if EGM96_15.exists():
            assert GeoidGrid.from_gtx(EGM96_15).undulation(lat, lon) == pytest.approx(
                undulation_m, abs=0.5
            )

    def test_longitudes_wrap_at_the_antimeridian(self) -> None:
        geoid = bundled_geoid()
        east, west = geoid.undulation(10.0, 179.99), geoid.undulation(10.0, -179.99)
        assert east is not None
        assert west is not None
        assert east == pytest.approx(west, abs=0.1)

    def test_gtx_grid_is_read_and_checked(self, tmp_path: Path) -> None:
        grid = tmp_path / "g.gtx"
        grid.write_bytes(
            struct.pack(">ddddii", 50.0, 10.0, 1.0, 1.0, 20, 20)
            + struct.pack(">400f", *[29.4] * 400)
        )
        assert GeoidGrid.from_gtx(grid).undulation(55.5, 15.5) == pytest.approx(29.4, abs=1e-4)
        assert GeoidGrid.from_gtx(grid).undulation(80.0, 15.5) is None
        grid.write_bytes(grid.read_bytes()[:100])
        with pytest.raises(ValueError, match="disagree"):
            GeoidGrid.from_gtx(grid)


class TestBlueForce:
    """Relayed friendly units (NFFI, CoT): friendly whatever the report says, never at 0,0."""

    def friend(self, **changes: object) -> BlueForce:
        values: dict[str, object] = {
            "event_id": "nffi-SWE.JAS39.39-7-1",
            "uid": "SWE.JAS39.39-7",
            "time": datetime(2026, 11, 22, 10, 10, tzinfo=UTC),
            "callsign": "GRIPEN-7",
            "position": Position(lat_deg=65.9, lon_deg=21.8, alt_msl_m=4000.0),
            "source": "nffi",
            "speed_mps": 250.0,
            "course_deg": 359.999,
            "sidc": "SFAPMFF--------",
        }
        return BlueForce.model_validate(values | changes)

    def test_typed_from_its_sidc_with_its_own_uid_course_and_speed(self) -> None:
        cot = build(self.friend(), CotOptions())
        assert cot is not None
        assert (cot.uid, cot.type, cot.how, cot.callsign) == (
            "SWE.JAS39.39-7", "a-f-A-M-F-F", "h-e", "GRIPEN-7",
        )  # fmt: skip
        assert (cot.course_deg, cot.speed_mps) == (0.0, 250.0)
        assert cot.stale - cot.time == timedelta(seconds=600)
        assert "COT_MAPPING_2525C/a-f/a-f-A-M-F-F" in cot.xml_detail

    def test_never_drawn_hostile_and_never_at_null_island(self) -> None:
        hostile = build(self.friend(sidc="SHGPUCI--------"), CotOptions())
        assert hostile is not None
        assert hostile.type == "a-f-G-U-C-I"
        plain = build(self.friend(sidc=None), CotOptions())
        assert plain is not None
        assert plain.type == "a-f-G"
        assert build(self.friend(position=Position(lat_deg=0.0, lon_deg=0.0)), CotOptions()) is None


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(
    st.text()
    | st.text(alphabet="abc.:-_ 0123&<>\"'\t\n\r\x00\x7f\ufffe")
    | st.sampled_from(["2026-11-27T08:00:00.123Z", "a-h-G-U-C", "fischer-det-F26E-001-det-7-1"])
)
def test_an_attribute_value_is_quoted_as_quoteattr_of_xml_safe_quotes_it(text: str) -> None:
    assert xml_attribute(text) == quoteattr(xml_safe(text))


class TestOrigin:
    """Another node's airframe, detection or fused track says its node in the remarks, as an
    independent decoder (lxml on the XML, takproto on the TAK protobuf) reads them."""

    @staticmethod
    def remarks(event: Telemetry | Detection | Track) -> list[str]:
        takproto = pytest.importorskip("takproto")
        etree = pytest.importorskip("lxml.etree")
        built = build(event, options())
        assert built is not None
        xml = etree.fromstring(to_xml(built))
        proto = takproto.parse_proto(bytearray(mesh_frame(to_proto(built)))).cotEvent
        detail = etree.fromstring(f"<detail>{proto.detail.xmlDetail}</detail>")
        found = [xml.findtext("detail/remarks"), detail.findtext("remarks")]
        assert found[0] == found[1]
        return found[:1]

    def test_remote_telemetry_and_detection_name_their_node(self) -> None:
        (telemetry,) = self.remarks(TELEMETRY.model_copy(update={"origin_node": "brigade-2"}))
        assert telemetry == "link sdr, from node brigade-2"
        (detection,) = self.remarks(DETECTION.model_copy(update={"origin_node": "b"}))
        assert detection == "IR detection: tank T-72, confidence 0.91; from node b"

    def test_own_events_name_no_node(self) -> None:
        assert self.remarks(TELEMETRY) == ["link sdr"]
        assert "node" not in self.remarks(DETECTION)[0]
        assert "node" not in self.remarks(TRACK)[0]

    def test_a_fused_track_names_every_contributing_node(self) -> None:
        (remarks,) = self.remarks(TRACK.model_copy(update={"origin_nodes": ("b", "c_2")}))
        assert remarks.endswith("CEP90 36 m; detections from nodes b, c_2")

    def test_remarks_stay_short_with_the_most_nodes_and_longest_names(self) -> None:
        nodes = tuple(f"{n:02d}" + "n" * 30 for n in range(MAX_TRACK_NODES))
        track = Track.model_validate({**TRACK.model_dump(), "origin_nodes": nodes})
        (remarks,) = self.remarks(track)
        assert remarks.endswith(", ".join(nodes))
        assert len(remarks) < 800
        with pytest.raises(ValueError, match="at most 16"):
            Track.model_validate({**TRACK.model_dump(), "origin_nodes": (*nodes, "x")})
        with pytest.raises(ValueError, match="pattern"):
            DETECTION.model_validate({**DETECTION.model_dump(), "origin_node": "b<x>"})
