"""The tracker: sensor frames assigned jointly, Mahalanobis gating, M-of-N track life, the
per-class speed prior, merges published as merges, strictly newer times. Time comes only
from the detections and ``tick``."""

from __future__ import annotations

import math
from collections import defaultdict
from datetime import UTC, datetime, timedelta
from itertools import count, pairwise
from unittest.mock import patch

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.domain.targeting import CEP50_FACTOR
from gateway.events import BOOT_ID, Detection, Position, Sensor, Track
from gateway.fleet.dialect import CLASS_NAMES
from gateway.flow.localplane import displace, offset_m
from tracking import DEFAULT_CLASSES, Tracker, TrackerSettings

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
    origin_node: str | None = None,
    frame_size: int | None = None,
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
        origin_node=origin_node,
        frame_size=frame_size,
    )


def at(t_s: float) -> datetime:
    return T0 + timedelta(seconds=t_s)


def confirmed(tracker: Tracker, **kw: object) -> list[Track]:
    """Three frames of one detection each, a second apart: M of N confirms the track."""
    out: list[Track] = []
    t0 = float(kw.pop("t_s", 0.0))  # type: ignore[arg-type]
    for i in range(3):
        out += tracker.update_frame([detection(t_s=t0 + i, **kw)])  # type: ignore[arg-type]
    return out


class TestFrames:
    """A frame (airframe, sensor, time) is processed whole, once it is complete."""

    def test_a_frame_waits_for_the_next_frame_of_its_source_or_a_flush(self) -> None:
        tracker = Tracker(TrackerSettings(confirm_hits=1))
        assert tracker.update(detection(t_s=0.0)) == []
        assert tracker.update(detection(t_s=0.0, east_m=500.0)) == []
        assert len(tracker) == 0  # still held
        created = tracker.update(detection(t_s=1.0))
        assert [t.status for t in created] == ["created", "created"]
        assert tracker.counts.frames == 1
        assert [t.status for t in tracker.flush()] == ["updated"]

    def test_a_frame_that_says_its_size_is_processed_once_it_holds_that_many(self) -> None:
        tracker = Tracker(TrackerSettings(confirm_hits=1))
        assert tracker.update(detection(t_s=0.0, frame_size=2)) == []
        assert tracker.holding
        created = tracker.update(detection(t_s=0.0, east_m=500.0, frame_size=2))
        assert [t.status for t in created] == ["created", "created"]
        assert not tracker.holding
        assert tracker.counts.frames == 1

    def test_a_size_larger_than_sent_waits_as_a_frame_without_one(self) -> None:
        tracker = Tracker(TrackerSettings(confirm_hits=1))
        assert tracker.update(detection(t_s=0.0, frame_size=3)) == []
        assert tracker.update(detection(t_s=0.0, east_m=500.0, frame_size=3)) == []
        assert tracker.holding
        assert [t.status for t in tracker.flush()] == ["created", "created"]
        assert tracker.counts.frames == 1

    def test_sizes_that_differ_wait_for_the_largest(self) -> None:
        tracker = Tracker(TrackerSettings(confirm_hits=1))
        assert tracker.update(detection(t_s=0.0, frame_size=3)) == []
        assert tracker.update(detection(t_s=0.0, east_m=500.0, frame_size=2)) == []
        created = tracker.update(detection(t_s=0.0, east_m=1000.0, frame_size=1))
        assert [t.status for t in created] == ["created"] * 3
        assert tracker.counts.frames == 1

    def test_a_size_too_small_processes_early_and_a_late_mate_is_a_frame_of_its_own(
        self,
    ) -> None:
        tracker = Tracker(TrackerSettings(confirm_hits=1))
        assert [t.status for t in tracker.update(detection(t_s=0.0, frame_size=1))] == ["created"]
        # Its frame-mate came after the frame was taken: held as a frame of its own.
        assert tracker.update(detection(t_s=0.0, east_m=500.0)) == []
        assert [t.status for t in tracker.flush()] == ["created"]
        assert tracker.counts.frames == 2
        assert len(tracker) == 2

    def test_two_detections_of_one_frame_never_go_to_one_track(self) -> None:
        """Greedy association gave both to the nearer track; jointly, each gets its own."""
        tracker = Tracker(TrackerSettings(confirm_hits=1))
        tracker.update_frame([detection(east_m=0.0), detection(east_m=60.0)])
        assert len(tracker) == 2
        before = tracker.counts.created
        # Both shift 25 m east: the west one is now nearer the east track's old position
        # than its own, but only one of them may go to each track.
        tracker.update_frame([detection(t_s=1.0, east_m=25.0), detection(t_s=1.0, east_m=85.0)])
        assert tracker.counts.created == before
        assert tracker.counts.associated == 2


class TestTrackLife:
    """Tentative, confirmed (M of N), coasting, deleted; only confirmed tracks published."""

    def test_one_detection_is_never_published_and_is_dropped_quietly(self) -> None:
        tracker = Tracker(TrackerSettings(coast_after_s=3.0))
        assert tracker.update_frame([detection()]) == []
        assert tracker.stage(tracker.track_ids[0]) == "tentative"
        assert tracker.tick(at(3.5)) == []
        assert len(tracker) == 0
        assert tracker.counts.discarded == 1

    def test_the_third_detection_confirms_and_publishes_created(self) -> None:
        tracker = Tracker()
        assert tracker.update_frame([detection(t_s=0.0)]) == []
        assert tracker.update_frame([detection(t_s=1.0, east_m=2.0)]) == []
        (created,) = tracker.update_frame([detection(t_s=2.0, east_m=-1.0)])
        assert created.status == "created"
        assert created.detection_count == 3
        assert created.track_id.startswith(f"T-{BOOT_ID}-")
        assert tracker.confirmed_ids == [created.track_id]

    def test_a_tentative_track_missed_too_often_is_dropped(self) -> None:
        """M=3 of N=5: three misses (a frame of a source that saw it, with a detection in its
        gate that went to another track) end it, before it could be confirmed."""
        tracker = Tracker()
        tracker.update_frame([detection(sigma_m=5.0), detection(sigma_m=5.0, east_m=40.0)])
        for i in range(1, 3):  # only the east object is seen again, inside both gates
            tracker.update_frame([detection(t_s=0.2 * i, sigma_m=5.0, east_m=40.0)])
        assert len(tracker) == 2
        tracker.update_frame([detection(t_s=0.6, sigma_m=5.0, east_m=40.0)])
        assert tracker.counts.discarded == 1
        assert len(tracker) == 1
        assert tracker.confirmed_ids == tracker.track_ids

    def test_a_tentative_track_not_seen_again_is_dropped_quietly(self) -> None:
        tracker = Tracker(TrackerSettings(coast_after_s=3.0))
        tracker.update_frame([detection(), detection(t_s=1.0)])
        assert tracker.tick(at(4.5)) == []
        assert len(tracker) == 0
        assert tracker.counts.discarded == 1

    def test_silence_coasts_then_loses_once(self) -> None:
        tracker = Tracker(TrackerSettings(coast_after_s=3.0, lost_after_s=30.0))
        (created,) = confirmed(tracker)
        assert tracker.tick(at(4.0)) == []  # its last detection came at 2 s
        assert tracker.stage(created.track_id) == "confirmed"
        assert tracker.tick(at(5.0)) == []
        assert tracker.stage(created.track_id) == "coasting"
        assert tracker.tick(at(31.0)) == []
        (lost,) = tracker.tick(at(32.0))
        assert lost.status == "lost"
        assert lost.track_id == created.track_id
        assert lost.time == at(32.0)
        assert len(tracker) == 0
        assert tracker.tick(at(60.0)) == []

    def test_a_coasting_track_is_taken_up_again(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        (created,) = confirmed(tracker, object_class="tank", sigma_m=5.0)
        tracker.tick(at(10.0))
        assert tracker.stage(created.track_id) == "coasting"
        (again,) = tracker.update_frame([detection(t_s=20.0, object_class="tank", sigma_m=5.0)])
        assert again.track_id == created.track_id
        assert tracker.stage(created.track_id) == "confirmed"

    def test_updates_are_coalesced_and_flushed_by_tick(self) -> None:
        tracker = Tracker()
        (created,) = confirmed(tracker)
        assert tracker.update_frame([detection(t_s=2.2, airframe="B")]) == []
        (flushed,) = tracker.tick(at(3.0))
        assert flushed.status == "updated"
        assert flushed.detection_count == 4
        assert flushed.event_id != created.event_id

    def test_full_tracker_refuses_new_tracks(self) -> None:
        tracker = Tracker(TrackerSettings(max_tracks=3))
        tracker.update_frame([detection(east_m=i * 10_000.0) for i in range(5)])
        assert len(tracker) == 3
        assert tracker.counts.refused_full == 2


class TestGate:
    """Mahalanobis d² against the constant-velocity prediction, at most gate_sigma²."""

    @pytest.mark.parametrize(("distance_m", "tracks"), [(56.0, 1), (57.0, 2)])
    def test_gate_of_a_new_track_is_its_covariance_plus_the_detections(
        self, distance_m: float, tracks: int
    ) -> None:
        """σ 10 and 10 at one instant: S = 200 m² per axis, the 4σ gate √200·4 ≈ 56.6 m."""
        tracker = Tracker()
        tracker.update_frame([detection(sigma_m=10.0)])
        tracker.update_frame([detection(airframe="B", sigma_m=10.0, east_m=distance_m)])
        assert len(tracker) == tracks

    def test_the_class_speed_limit_bounds_a_new_tracks_gate(self) -> None:
        """200 m in a second: plausible for a UAV (70 m/s), not for a tank (20 m/s)."""
        for cls, tracks in (("uav", 1), ("tank", 2)):
            tracker = Tracker()
            tracker.update_frame([detection(object_class=cls)])
            tracker.update_frame([detection(t_s=1.0, object_class=cls, east_m=200.0)])
            assert len(tracker) == tracks, cls

    def test_total_conflict_is_not_associated_and_is_counted(self) -> None:
        tracker = Tracker()
        tracker.update_frame([detection(object_class="tank", confidence=1.0)])
        tracker.update_frame([detection(airframe="B", object_class="uav", confidence=1.0)])
        assert len(tracker) == 2
        assert tracker.counts.total_conflict == 1


class TestEstimate:
    """A Kalman filter per track: velocity, CEP, the speed prior that penalises."""

    def test_velocity_and_course_of_a_moving_target(self) -> None:
        speed, course = 30.0, 60.0
        ve, vn = speed * math.sin(math.radians(course)), speed * math.cos(math.radians(course))
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        last: list[Track] = []
        for i in range(20):
            t = i * 0.5
            last = tracker.update_frame(
                [detection(t_s=t, east_m=ve * t, north_m=vn * t, airframe="AB"[i % 2], sigma_m=5.0)]
            )
        (track,) = last
        assert len(tracker) == 1
        assert track.speed_mps == pytest.approx(speed, rel=0.05)
        assert track.course_deg == pytest.approx(course, abs=2.0)
        assert track.velocity is not None
        east, north = offset_m(LAT, LON, track.position.lat_deg, track.position.lon_deg)
        assert east == pytest.approx(ve * 9.5, abs=5.0)
        assert north == pytest.approx(vn * 9.5, abs=5.0)

    def test_velocity_is_withheld_until_it_is_known(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        (created,) = confirmed(tracker, sigma_m=15.0)
        assert created.velocity is None
        assert created.speed_mps is None

    def test_cep_shrinks_with_more_detections(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0, confirm_hits=1))
        ceps: list[float] = []
        for i in range(5):
            (track,) = tracker.update_frame([detection(airframe=f"A{i}", sigma_m=10.0)])
            ceps.append(track.cep50_m)
        assert ceps[0] == pytest.approx(10.0 * CEP50_FACTOR)
        assert all(b < a for a, b in pairwise(ceps))
        assert ceps[-1] == pytest.approx(10.0 / math.sqrt(5) * CEP50_FACTOR)

    def test_the_speed_limit_penalises_but_never_clamps(self) -> None:
        """A 'tank' at 30 m/s (its limit is 20): pulled back, still faster than the limit."""
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        last: list[Track] = []
        for i in range(30):
            last = tracker.update_frame(
                [detection(t_s=float(i), east_m=30.0 * i, object_class="tank", sigma_m=5.0)]
            )
        (track,) = last
        assert len(tracker) == 1
        assert track.speed_mps is not None
        assert 20.0 < track.speed_mps < 30.0
        assert tracker.counts.speed_prior > 0


class TestClassEvidence:
    """Each source's newest report, combined with Dempster's rule."""

    def test_seed_eo_080_and_ir_075_from_two_airframes_give_095_in_one_track(self) -> None:
        tracker = Tracker()
        tracker.update_frame([detection(t_s=0.0, confidence=0.80)])
        tracker.update_frame([detection(t_s=1.0, confidence=0.80, east_m=2.0)])
        (created,) = tracker.update_frame(
            [detection(t_s=1.3, airframe="B", sensor=Sensor.IR, confidence=0.75, east_m=3.0)]
        )
        assert created.status == "created"
        assert created.confidence == pytest.approx(0.95)
        assert created.airframes == ("A", "B")
        assert created.sensors == (Sensor.EO, Sensor.IR)
        assert created.hostility == "hostile"
        assert created.sidc is not None

    def test_default_frame_is_the_dialects_classes(self) -> None:
        assert set(DEFAULT_CLASSES) == set(CLASS_NAMES.values())


class TestOriginNodes:
    """A track names the other nodes whose detections it holds (bounded), never this one."""

    def test_detections_of_two_other_nodes_and_our_own_name_the_two_nodes(self) -> None:
        tracker = Tracker(TrackerSettings(confirm_hits=1, update_interval_s=0.0))
        (created,) = tracker.update_frame([detection(t_s=0.0)])
        assert created.origin_nodes == ()
        tracker.update_frame([detection(t_s=1.0, airframe="B", origin_node="c", east_m=1.0)])
        updates = tracker.update_frame(
            [detection(t_s=2.0, airframe="C", origin_node="b", east_m=2.0)]
        )
        assert updates[-1].track_id == created.track_id
        assert updates[-1].origin_nodes == ("b", "c")
        assert updates[-1].airframes == ("A", "B", "C")

    def test_at_most_sixteen_nodes_the_first_heard(self) -> None:
        tracker = Tracker(TrackerSettings(confirm_hits=1, update_interval_s=0.0))
        events: list[Track] = []
        for n in range(24):  # node n24 .. n01: heard in reverse order of their names
            node = f"n{24 - n:02d}"
            events += tracker.update_frame(
                [detection(t_s=float(n), airframe=f"X{n}", origin_node=node, east_m=n * 0.5)]
            )
        assert len({e.track_id for e in events}) == 1
        assert events[-1].origin_nodes == tuple(f"n{k:02d}" for k in range(9, 25))


class TestMerge:
    """A second track of one object is folded into the first and published as merged."""

    def test_twin_is_published_as_merged_naming_the_survivor_never_lost(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        events: list[Track] = []
        for i in range(40):  # B's reports start 60 m off and close in on A's, then agree
            events += tracker.update_frame([detection(t_s=i, object_class="tank", sigma_m=5.0)])
            events += tracker.update_frame(
                [detection(t_s=i + 0.5, airframe="B", sensor=Sensor.IR, object_class="tank",
                           sigma_m=5.0, east_m=max(0.0, 60.0 - 3.0 * i), origin_node="b")]
            )  # fmt: skip
        created = [e for e in events if e.status == "created"]
        assert len(created) == 2
        first, second = created
        (merged,) = [e for e in events if e.status == "merged"]
        assert merged.track_id == second.track_id
        assert merged.merged_into == first.track_id
        assert not [e for e in events if e.status == "lost"]
        assert tracker.counts.merged == 1
        assert tracker.track_ids == [first.track_id]
        after = [e for e in events if e.track_id == first.track_id and e.time > merged.time]
        assert after
        assert set(after[-1].airframes) == {"A", "B"}
        assert after[-1].origin_nodes == ("b",)  # B's node came with the folded track
        assert first.origin_nodes == ()

    def test_two_objects_side_by_side_are_never_merged(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0))
        for i in range(20):
            tracker.update_frame(
                [detection(t_s=i, sigma_m=5.0), detection(t_s=i, sigma_m=5.0, east_m=30.0)]
            )
        assert len(tracker) == 2
        assert tracker.counts.merged == 0


frames = st.lists(
    st.lists(
        st.tuples(
            st.integers(min_value=0, max_value=5),  # object
            st.floats(min_value=-40.0, max_value=40.0),  # noise east
            st.floats(min_value=-40.0, max_value=40.0),  # noise north
            st.sampled_from([*DEFAULT_CLASSES, "bicycle"]),
            st.sampled_from([0.3, 0.6, 0.9, 1.0]),
            st.floats(min_value=2.0, max_value=60.0),  # σ
        ),
        min_size=1,
        max_size=6,
    ),
    min_size=1,
    max_size=12,
)


def _stream(spec: list[list[tuple[int, float, float, str, float, float]]]) -> list[Detection]:
    """Frame k at k/2 s alternately from A/EO and B/IR; objects 120 m apart, moving."""
    out = []
    for k, frame in enumerate(spec):
        t = 0.5 * k
        airframe, sensor = (("A", Sensor.EO), ("B", Sensor.IR))[k % 2]
        for n, (obj, de, dn, cls, conf, sigma) in enumerate(frame):
            out.append(
                Detection(
                    event_id=f"{airframe}-{k}-{n}",
                    airframe=airframe,
                    time=T0 + timedelta(seconds=t),
                    sensor=sensor,
                    object_class=cls,
                    confidence=conf,
                    position=Position(
                        lat_deg=displace(LAT, LON, obj * 120.0 + 8.0 * t + de, dn - 3.0 * t)[0],
                        lon_deg=displace(LAT, LON, obj * 120.0 + 8.0 * t + de, dn - 3.0 * t)[1],
                    ),
                    sigma_h_m=sigma,
                )
            )
    return out


def _run(tracker: Tracker, stream: list[Detection]) -> list[Track]:
    out: list[Track] = []
    for d in stream:
        out += tracker.update(d)
    return out + tracker.tick(stream[-1].time + timedelta(seconds=1))


@settings(max_examples=60, deadline=None)
@given(spec=frames, data=st.data())
def test_permuting_a_frames_detections_never_changes_the_tracks(
    spec: list[list[tuple[int, float, float, str, float, float]]], data: st.DataObject
) -> None:
    stream = _stream(spec)
    frames_of: dict[datetime, list[Detection]] = defaultdict(list)
    for d in stream:
        frames_of[d.time].append(d)
    shuffled = [d for t in sorted(frames_of) for d in data.draw(st.permutations(frames_of[t]))]
    settings_ = TrackerSettings(confirm_hits=2, confirm_window=3, update_interval_s=0.0)
    one, two = Tracker(settings_), Tracker(settings_)
    assert _run(one, stream) == _run(two, shuffled)
    assert one.counts == two.counts


@settings(max_examples=40, deadline=None)
@given(spec=frames)
def test_frames_that_say_their_size_give_the_tracks_of_frames_that_wait(
    spec: list[list[tuple[int, float, float, str, float, float]]],
) -> None:
    """``frame_size`` only decides when a frame is taken, never what it makes."""
    stream = _stream(spec)
    sizes: dict[tuple[str, datetime], int] = defaultdict(int)
    for d in stream:
        sizes[d.airframe, d.time] += 1
    sized = [d.model_copy(update={"frame_size": sizes[d.airframe, d.time]}) for d in stream]
    settings_ = TrackerSettings(confirm_hits=2, confirm_window=3, update_interval_s=0.0)
    waiting, told = Tracker(settings_), Tracker(settings_)
    expected = _run(waiting, stream)
    events = [track for d in sized for track in told.update(d)]
    assert not told.holding  # every frame was taken as it completed
    assert events + told.tick(stream[-1].time + timedelta(seconds=1)) == expected
    assert waiting.counts == told.counts


@settings(max_examples=40, deadline=None)
@given(spec=frames, cell=st.sampled_from([20.0, 200.0, 2000.0]))
def test_grid_and_all_pairs_give_identical_tracks_with_strictly_newer_times(
    spec: list[list[tuple[int, float, float, str, float, float]]], cell: float
) -> None:
    """The grid only narrows the candidates; the gate decides. And per track, every event
    carries a strictly newer time than the one before. (The grid is queried even for the few
    tracks these streams make: below ``_FEW`` it would not be.)"""
    from tracking import index as index_module

    stream = _stream(spec)
    common = {"confirm_hits": 2, "confirm_window": 3, "update_interval_s": 0.0}
    grid = Tracker(TrackerSettings(index="grid", cell_m=cell, **common))  # type: ignore[arg-type]
    pairs = Tracker(TrackerSettings(index="all_pairs", **common))  # type: ignore[arg-type]
    with patch.object(index_module, "_FEW", 0):
        events = _run(grid, stream)
    assert events == _run(pairs, stream)
    last: dict[str, datetime] = {}
    for event in events:
        assert event.time > last.get(event.track_id, datetime.min.replace(tzinfo=UTC))
        last[event.track_id] = event.time


def spot(n: int) -> dict[str, float]:
    return {"east_m": (n % 20) * 100.0, "north_m": (n // 20) * 100.0}


class TestCrowdedFrames:
    """A crafted frame cannot make the tracker examine more than its pair budget."""

    def test_a_frame_past_the_pair_budget_refuses_the_rest_and_counts_them(self) -> None:
        from tracking import tracker as module

        tracker = Tracker(TrackerSettings(confirm_hits=1, max_tracks=5000))
        # 300 tracks 100 m apart in a 2 x 1.5 km block, one frame each (other airframes).
        for n in range(300):
            tracker.update_frame([detection(**spot(n), sensor=Sensor.IR, airframe=f"B{n}")])
        assert len(tracker) == 300
        # One frame of 300 detections on them: every detection is a candidate for every track.
        crowd = [detection(t_s=1, **spot(n)) for n in range(300)]
        tracker.update_frame(crowd)
        # Each detection is a candidate for the tracks of its grid cells (2 km): most of them.
        assert 0 < tracker.counts.overload_refused < 300
        assert module.MAX_FRAME_PAIRS < 300 * 300
        # What was refused is the end of the frame's canonical order, whatever the arrival order.
        again = Tracker(TrackerSettings(confirm_hits=1, max_tracks=5000))
        for n in range(300):
            again.update_frame([detection(**spot(n), sensor=Sensor.IR, airframe=f"B{n}")])
        again.update_frame(list(reversed([d.model_copy() for d in crowd])))
        assert again.counts.overload_refused == tracker.counts.overload_refused
        assert sorted(again.confirmed_ids) == sorted(tracker.confirmed_ids)

    def test_a_real_frame_is_far_inside_the_budget(self) -> None:
        from tracking import tracker as module

        tracker = Tracker(TrackerSettings(confirm_hits=1))
        for t in range(3):  # a column of 20 vehicles 50 m apart, seen whole each second
            tracker.update_frame([detection(t_s=t, east_m=50.0 * n + 10.0 * t) for n in range(20)])
        assert tracker.counts.overload_refused == 0
        assert module.MAX_FRAME_PAIRS > 20 * 20


class TestVagueDetections:
    """A detection too vague to place anything cannot keep a track alive from afar."""

    def test_a_detection_vaguer_than_max_sigma_is_refused_and_the_track_is_lost(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0, lost_after_s=20.0))
        events: list[Track] = []
        for i in range(5):
            events += tracker.update_frame([detection(t_s=i)])
        # Then only a 9 km σ report from another airframe, 3 km north, every second.
        for i in range(5, 40):
            events += tracker.update_frame(
                [detection(t_s=i, airframe="B", sensor=Sensor.IR, north_m=3000.0, sigma_m=9000.0)]
            )
            events += tracker.tick(T0 + timedelta(seconds=i))
        assert tracker.counts.too_vague == 35
        assert [e.status for e in events if e.status != "updated"] == ["created", "lost"]

    def test_a_sigma_below_a_metre_counts_as_a_metre(self) -> None:
        tracker = Tracker(TrackerSettings(update_interval_s=0.0, confirm_hits=1))
        (created,) = tracker.update_frame([detection(sigma_m=0.0)])
        assert created.cep50_m == pytest.approx(1.1774, abs=1e-3)  # CEP50 of σ 1 m
