"""The tracker: association gated in σ and time, Dempster-Shafer class evidence, estimation,
lifecycle and emission. Time comes only from the detections and ``tick``."""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta
from itertools import count, pairwise

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.domain.targeting import CEP50_FACTOR
from gateway.events import BOOT_ID, Detection, Position, Sensor, Track
from gateway.fleet.dialect import CLASS_NAMES
from gateway.flow.localplane import displace, offset_m
from gateway.flow.tracker import DEFAULT_CLASSES, Tracker, TrackerSettings

T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
LAT, LON = 65.8, 21.7
_ids = count(1)


def detection(
    *,
    t_s: float = 0.0,
    east_m: float = 0.0,
    north_m: float = 0.0,
    airframe: str = "A",
    sensor: Sensor = Sensor.EO,
    object_class: str = "loitering_munition",
    confidence: float = 0.8,
    sigma_m: float = 10.0,
    alt_msl_m: float | None = 300.0,
) -> Detection:
    lat, lon = displace(LAT, LON, east_m, north_m)
    return Detection(
        event_id=f"{airframe}-det-{next(_ids)}",
        airframe=airframe,
        time=T0 + timedelta(seconds=t_s),
        sensor=sensor,
        object_class=object_class,
        confidence=confidence,
        position=Position(lat_deg=lat, lon_deg=lon, alt_msl_m=alt_msl_m),
        sigma_h_m=sigma_m,
    )


def at(t_s: float) -> datetime:
    return T0 + timedelta(seconds=t_s)


class TestClassEvidence:
    """Each source's newest report, combined with Dempster's rule."""

    def test_seed_eo_080_and_ir_075_from_two_airframes_give_095_in_one_track(self) -> None:
        tracker = Tracker()
        (created,) = tracker.update(detection(airframe="A", sensor=Sensor.EO, confidence=0.80))
        updated = tracker.update(
            detection(t_s=1.0, airframe="B", sensor=Sensor.IR, confidence=0.75, east_m=3.0)
        )
        assert created.status == "created"
        assert created.confidence == pytest.approx(0.80)
        assert [t.status for t in updated] == ["updated"]
        assert updated[0].track_id == created.track_id
        assert updated[0].confidence == pytest.approx(0.95)
        assert updated[0].class_conflict == 0.0
        assert updated[0].airframes == ("A", "B")
        assert updated[0].sensors == (Sensor.EO, Sensor.IR)
        assert updated[0].object_class == "loitering_munition"
        assert updated[0].hostility == "hostile"
        assert updated[0].sidc is not None
        assert tracker.counts.associated == 1
        assert tracker.counts.created == 1

    def test_one_source_repeating_replaces_and_never_reaches_one(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        out: list[Track] = []
        for i in range(20):
            out += tracker.update(detection(t_s=i * 0.5, confidence=0.8))
        assert len(tracker) == 1
        assert out[-1].confidence == pytest.approx(0.8)

    def test_conflicting_sources_report_k_and_unknown_class_is_other(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        tracker.update(detection(object_class="uav", confidence=0.9))
        (track,) = tracker.update(
            detection(t_s=0.1, airframe="B", object_class="bicycle", confidence=0.5)
        )
        assert track.class_conflict == pytest.approx(0.45)
        assert track.object_class == "uav"
        assert track.hostility == "suspect"
        (track,) = tracker.update(
            detection(t_s=0.2, airframe="C", object_class="bicycle", confidence=0.99)
        )
        assert track.object_class == "other"
        assert track.sidc is None

    def test_total_conflict_is_not_associated_and_is_counted(self) -> None:
        tracker = Tracker()
        (first,) = tracker.update(detection(object_class="tank", confidence=1.0))
        (second,) = tracker.update(
            detection(t_s=0.5, airframe="B", object_class="uav", confidence=1.0)
        )
        assert second.status == "created"
        assert second.track_id != first.track_id
        assert tracker.counts.total_conflict == 1
        assert len(tracker) == 2

    def test_default_frame_is_the_dialects_classes(self) -> None:
        assert set(DEFAULT_CLASSES) == set(CLASS_NAMES.values())


class TestAssociation:
    """Gated in combined σ around the constant-velocity prediction, and in time."""

    def test_two_airframes_one_target_make_one_track(self) -> None:
        tracker = Tracker()
        events: list[Track] = []
        for i in range(10):
            events += tracker.update(detection(t_s=i, airframe="A", east_m=i % 3))
            events += tracker.update(
                detection(t_s=i + 0.3, airframe="B", sensor=Sensor.IR, north_m=-(i % 2))
            )
        assert len(tracker) == 1
        assert {t.track_id for t in events} == {tracker.track_ids[0]}
        assert tracker.track_ids[0].startswith(f"T-{BOOT_ID}-")

    def test_well_separated_targets_stay_two_tracks(self) -> None:
        tracker = Tracker()
        for i in range(10):
            tracker.update(detection(t_s=i, airframe="A"))
            tracker.update(detection(t_s=i + 0.2, airframe="B", east_m=5000.0))
        assert len(tracker) == 2
        assert tracker.counts.associated == 18

    @pytest.mark.parametrize(("distance_m", "tracks"), [(42.0, 1), (43.0, 2)])
    def test_gate_is_in_combined_sigma(self, distance_m: float, tracks: int) -> None:
        """σ 10 and 10 at the same instant: the 3σ gate is 3·√200 ≈ 42.43 m."""
        tracker = Tracker()
        tracker.update(detection(sigma_m=10.0))
        tracker.update(detection(airframe="B", sigma_m=10.0, east_m=distance_m))
        assert len(tracker) == tracks

    def test_gate_sigma_is_configurable(self) -> None:
        tracker = Tracker(TrackerSettings(gate_sigma=5.0))
        tracker.update(detection(sigma_m=10.0))
        tracker.update(detection(airframe="B", sigma_m=10.0, east_m=60.0))
        assert len(tracker) == 1

    def test_a_track_older_than_max_gap_is_not_associated(self) -> None:
        tracker = Tracker(TrackerSettings(max_gap_s=5.0))
        tracker.update(detection())
        tracker.update(detection(t_s=6.0))
        assert len(tracker) == 2
        assert tracker.counts.associated == 0

    def test_best_candidate_wins(self) -> None:
        tracker = Tracker()
        (a,) = tracker.update(detection(sigma_m=5.0))
        (b,) = tracker.update(detection(airframe="B", sigma_m=5.0, east_m=40.0))
        (near_b,) = tracker.update(detection(t_s=1.5, airframe="C", sigma_m=5.0, east_m=28.0))
        assert a.track_id != b.track_id
        assert near_b.track_id == b.track_id


class TestEstimation:
    """Position fused by inverse variance, velocity fitted, CEP from the fused σ."""

    def test_velocity_and_course_of_a_moving_target(self) -> None:
        speed, course = 30.0, 60.0
        ve, vn = speed * math.sin(math.radians(course)), speed * math.cos(math.radians(course))
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        last: list[Track] = []
        for i in range(20):
            t = i * 0.5
            last = tracker.update(
                detection(t_s=t, east_m=ve * t, north_m=vn * t, airframe="AB"[i % 2], sigma_m=5.0)
            )
        (track,) = last
        assert len(tracker) == 1
        assert track.speed_mps == pytest.approx(speed, rel=0.05)
        assert track.course_deg == pytest.approx(course, abs=2.0)
        assert track.velocity is not None
        assert track.velocity.east_mps == pytest.approx(ve, rel=0.05)
        assert track.velocity.down_mps == 0.0
        east, north = offset_m(LAT, LON, track.position.lat_deg, track.position.lon_deg)
        assert east == pytest.approx(ve * 9.5, abs=5.0)
        assert north == pytest.approx(vn * 9.5, abs=5.0)

    def test_course_is_within_0_and_360(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        last: list[Track] = []
        for i in range(6):
            last = tracker.update(detection(t_s=i, east_m=-10.0 * i, north_m=0.1 * i))
        assert last[0].course_deg is not None
        assert last[0].course_deg == pytest.approx(270.0, abs=2.0)

    def test_cep_shrinks_with_more_detections(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        ceps: list[float] = []
        for i in range(5):
            (track,) = tracker.update(detection(airframe=f"A{i}", sigma_m=10.0))
            ceps.append(track.cep50_m)
        assert ceps[0] == pytest.approx(10.0 * CEP50_FACTOR)
        assert all(b < a for a, b in pairwise(ceps))
        assert ceps[-1] == pytest.approx(10.0 / math.sqrt(5) * CEP50_FACTOR)

    def test_altitude_is_the_newest_known(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        tracker.update(detection(alt_msl_m=100.0))
        (track,) = tracker.update(detection(t_s=0.5, alt_msl_m=None))
        assert track.position.alt_msl_m == 100.0
        (track,) = tracker.update(detection(t_s=1.0, alt_msl_m=120.0))
        assert track.position.alt_msl_m == 120.0

    def test_detection_ids_keep_the_newest_32(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        sent = [detection(t_s=i * 0.1) for i in range(40)]
        last: list[Track] = []
        for d in sent:
            last = tracker.update(d)
        assert last[0].detection_ids == tuple(d.event_id for d in sent[-32:])
        assert last[0].detection_count == 40


class TestLifecycle:
    """Created, coalesced updates, lost; bounded."""

    def test_updates_are_coalesced_and_flushed_by_tick(self) -> None:
        tracker = Tracker()
        (created,) = tracker.update(detection())
        assert tracker.update(detection(t_s=0.2, airframe="B")) == []
        assert tracker.update(detection(t_s=0.4, airframe="C")) == []
        assert tracker.tick(at(0.6)) == []
        (flushed,) = tracker.tick(at(1.0))
        assert flushed.status == "updated"
        assert flushed.detection_count == 3
        assert flushed.event_id != created.event_id
        assert tracker.tick(at(2.5)) == []
        (due,) = tracker.update(detection(t_s=2.6))
        assert due.status == "updated"

    def test_a_class_change_is_emitted_at_once(self) -> None:
        tracker = Tracker()
        tracker.update(detection(object_class="uav", confidence=0.6))
        (changed,) = tracker.update(
            detection(t_s=0.1, airframe="B", object_class="tank", confidence=0.9)
        )
        assert changed.object_class == "tank"

    def test_a_silent_track_is_lost_once_and_forgotten(self) -> None:
        tracker = Tracker(TrackerSettings(lost_after_s=30.0))
        (created,) = tracker.update(detection())
        assert tracker.tick(at(29.0)) == []
        (lost,) = tracker.tick(at(30.0))
        assert lost.status == "lost"
        assert lost.track_id == created.track_id
        assert lost.time == at(30.0)
        assert len(tracker) == 0
        assert tracker.tick(at(60.0)) == []
        assert tracker.counts.lost == 1

    def test_full_tracker_refuses_new_tracks(self) -> None:
        tracker = Tracker(TrackerSettings(max_tracks=3))
        for i in range(5):
            tracker.update(detection(east_m=i * 10_000.0))
        assert len(tracker) == 3
        assert tracker.counts.refused_full == 2
        (updated,) = tracker.update(detection(t_s=2.0, airframe="B"))
        assert updated.status == "updated"

    def test_event_ids_are_unique_per_emission(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0, lost_after_s=5.0))
        events: list[Track] = []
        for i in range(5):
            events += tracker.update(detection(t_s=i * 0.5))
        events += tracker.tick(at(100.0))
        assert [e.status for e in events] == ["created"] + ["updated"] * 4 + ["lost"]
        assert len({e.event_id for e in events}) == len(events)


stream = st.lists(
    st.tuples(
        st.floats(min_value=0.0, max_value=0.5),  # seconds after the previous detection
        st.integers(min_value=0, max_value=7),  # target
        st.sampled_from(["A", "B", "C"]),
        st.sampled_from(list(Sensor)),
        st.sampled_from([*DEFAULT_CLASSES, "bicycle"]),
        st.sampled_from([0.3, 0.6, 0.9, 1.0]),
        st.floats(min_value=1.0, max_value=200.0),
        st.floats(min_value=-1500.0, max_value=1500.0),
        st.floats(min_value=-1500.0, max_value=1500.0),
    ),
    max_size=60,
)


@settings(max_examples=60, deadline=None)
@given(stream=stream, cell=st.sampled_from([20.0, 200.0, 2000.0]))
def test_grid_and_all_pairs_give_identical_tracks(
    stream: list[tuple[float, int, str, Sensor, str, float, float, float, float]], cell: float
) -> None:
    """The grid only narrows the candidates; the gate decides, so the tracks are the same.

    Targets kilometres apart with detections scattered around them, so the grid prunes and
    candidates fall on both sides of its query radius.
    """
    common = {"max_gap_s": 3.0, "lost_after_s": 4.0, "max_speed_mps": 20.0}
    grid = Tracker(TrackerSettings(index="grid", cell_m=cell, **common))
    pairs = Tracker(TrackerSettings(index="all_pairs", **common))
    t = 0.0
    for dt, target, airframe, sensor, cls, conf, sigma, de, dn in stream:
        t += dt
        d = detection(
            t_s=t,
            east_m=target * 3000.0 + 15.0 * t + de,
            north_m=target * 1800.0 - 8.0 * t + dn,
            airframe=airframe,
            sensor=sensor,
            object_class=cls,
            confidence=conf,
            sigma_m=sigma,
        )
        assert grid.update(d) == pairs.update(d)
        assert grid.tick(at(t)) == pairs.tick(at(t))
    assert grid.counts == pairs.counts


class TestTwins:
    """A second track on one target (a gate miss) is folded into the first once they meet."""

    def test_twin_tracks_of_one_target_merge_into_the_older(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        (first,) = tracker.update(detection(sigma_m=8.0))
        # The same target seen by another airframe 70 m off: outside the gate, a second track.
        (second,) = tracker.update(
            detection(airframe="B", sensor=Sensor.IR, sigma_m=8.0, east_m=70)
        )
        assert first.track_id != second.track_id
        for i in (1, 2):  # each airframe keeps its own estimate for a moment: two tracks
            tracker.update(detection(t_s=0.2 * i, sigma_m=8.0))
            tracker.update(
                detection(
                    t_s=0.2 * i + 0.05, airframe="B", sensor=Sensor.IR, sigma_m=8.0, east_m=70
                )
            )
        assert len(tracker) == 2
        events: list[Track] = []
        for i in range(3, 14):  # both sensors now report it between the two, where it is
            events += tracker.update(
                detection(t_s=0.5 * i, airframe="AB"[i % 2], sensor=[Sensor.EO, Sensor.IR][i % 2],
                          sigma_m=8.0, east_m=35.0)
            )  # fmt: skip
        assert tracker.counts.merged == 1
        assert tracker.track_ids == [first.track_id]
        (lost,) = [e for e in events if e.status == "lost"]
        assert lost.track_id == second.track_id
        final = [e for e in events if e.track_id == first.track_id][-1]
        assert set(final.airframes) == {"A", "B"}
        assert final.confidence == pytest.approx(1 - 0.2 * 0.2)  # EO 0.8 and IR 0.8, one each

    def test_two_targets_side_by_side_are_never_merged(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        for i in range(20):
            tracker.update(detection(t_s=0.5 * i, airframe="A", sigma_m=5.0))
            tracker.update(detection(t_s=0.5 * i + 0.1, airframe="B", sigma_m=5.0, east_m=60.0))
        assert len(tracker) == 2
        assert tracker.counts.merged == 0
