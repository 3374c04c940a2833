"""The scorer on hand-made truth and tracks: GOSPA per second, labels, switches, kinematics."""

from __future__ import annotations

import math

import pytest

from gateway.scoring.model import Plane, TrackReport, Tracks, TruthFrame, TruthRun, TruthTarget
from gateway.scoring.score import (
    Score,
    ScoreSettings,
    announcements_per_target,
    percentile,
    score,
)

T0 = 1_800_000_000.0
HALF = 100.0**2 / 2


def target(name: str, x: float, y: float = 0.0, vn: float = 0.0, ve: float = 0.0) -> TruthTarget:
    return TruthTarget(name, "tank", "hostile", x, y, vn, ve)


def run(*frames: tuple[TruthTarget, ...], speed: float = 1.0) -> TruthRun:
    ids = tuple(sorted({t.target for f in frames for t in f}))
    return TruthRun(
        scenario="hand",
        speed=speed,
        step_s=1.0,
        frames=tuple(TruthFrame(float(k), T0 + k / speed, f) for k, f in enumerate(frames)),
        plane=Plane(65.8, 21.7),
        target_ids=ids,
    )


def report(t: float, x: float, y: float = 0.0, status: str = "updated", **v: float) -> TrackReport:
    return TrackReport(T0 + t, x, y, v.get("vn"), v.get("ve"), status)


def tracks(**histories: list[TrackReport]) -> Tracks:
    out = Tracks()
    for track_id, history in histories.items():
        for r in history:
            out.add(track_id, r)
    out.sort()
    return out


class TestPicture:
    """Which tracks are on the picture at a truth second, and where."""

    def test_a_lost_track_leaves_the_picture(self) -> None:
        truth = run((target("A", 0.0),), (target("A", 0.0),))
        s = score(truth, tracks(T1=[report(0, 0.0), report(0.5, 0.0, status="lost")]))
        assert s.gospa_per_second == pytest.approx([0.0, math.sqrt(HALF)])

    def test_a_silent_track_leaves_after_max_age(self) -> None:
        truth = run(*[(target("A", 0.0),)] * 4)
        s = score(truth, tracks(T1=[report(0, 0.0)]), ScoreSettings(max_age_s=2.0))
        assert s.gospa_per_second == pytest.approx([0, 0, 0, math.sqrt(HALF)])

    def test_a_report_is_moved_on_by_its_own_velocity(self) -> None:
        truth = run((target("A", 0.0, ve=10.0),), (target("A", 10.0, ve=10.0),))
        s = score(truth, tracks(T1=[report(0, 0.0, vn=0.0, ve=10.0)]))
        assert s.gospa_per_second == pytest.approx([0.0, 0.0])

    def test_a_report_not_yet_made_is_not_shown(self) -> None:
        truth = run((target("A", 0.0),), (target("A", 0.0),))
        s = score(truth, tracks(T1=[report(1, 0.0)]))
        assert s.gospa_per_second == pytest.approx([math.sqrt(HALF), 0.0])


class TestRunMetrics:
    """Two targets, four tracks: one clean, one handed over (an ID switch), one false."""

    @pytest.fixture
    def result(self) -> Score:
        frames = [(target("A", 0.0), target("B", 1000.0)) for _ in range(3)]
        made = tracks(
            T1=[report(t, 3.0, 4.0) for t in range(3)],  # 5 m from A throughout
            T2=[report(0, 1000.0), report(1, 1000.0), report(1.5, 1000.0, status="lost")],
            T3=[report(2, 1006.0, 8.0)],  # takes over B: 10 m off
            T4=[report(t, 5000.0) for t in range(3)],  # nowhere near anything
        )
        return score(run(*frames), made)

    def test_gospa_per_second_and_its_mean(self, result: Score) -> None:
        expected = [
            math.sqrt(25 + 0 + HALF),
            math.sqrt(25 + 0 + HALF),
            math.sqrt(25 + 100 + HALF),
        ]
        assert result.gospa_per_second == pytest.approx(expected)
        assert result.gospa == pytest.approx(sum(expected) / 3)

    def test_tracks_per_target_false_tracks_and_switches(self, result: Score) -> None:
        assert result.tracks_of_target == {"A": ["T1"], "B": ["T2", "T3"]}
        assert result.tracks_per_target == pytest.approx(1.5)
        assert (result.false_tracks, result.track_ids) == (1, 4)
        assert result.false_track_share == pytest.approx(0.25)
        assert result.id_switches == 1

    def test_position_rmse_over_matched_seconds(self, result: Score) -> None:
        assert result.matched_pairs == 6
        assert result.position_rmse_m == pytest.approx(math.sqrt((3 * 25 + 0 + 0 + 100) / 6))

    def test_velocity_share_counts_non_terminal_reports(self, result: Score) -> None:
        assert result.velocity_share == 0.0  # no report carried a velocity


class TestKinematics:
    """Speed and course errors, in scenario units whatever the run's speed."""

    def test_speed_and_course_error_at_speed_4(self) -> None:
        # Truth: 10 m/s due east. The gateway sees 4x: 40 m/s. The track says 44 m/s at 090°
        # then 40 m/s at 045°... divided by 4: 11 m/s (error 1) and 10 m/s (error 0).
        truth = run((target("A", 0.0, ve=10.0),), (target("A", 40.0, ve=10.0),), speed=4.0)
        diagonal = 40.0 / math.sqrt(2)
        made = tracks(
            T1=[
                report(0.0, 0.0, vn=0.0, ve=44.0),
                report(0.25, 40.0, vn=diagonal, ve=diagonal),
            ]
        )
        s = score(truth, made)
        assert s.speed_error_median == pytest.approx(0.5)
        assert s.speed_error_p90 == pytest.approx(0.9)
        assert s.course_error_median == pytest.approx(22.5)
        assert s.velocity_share == 1.0

    def test_course_is_not_scored_for_a_stationary_target(self) -> None:
        truth = run((target("A", 0.0),))
        s = score(truth, tracks(T1=[report(0, 0.0, vn=3.0, ve=0.0)]))
        assert s.speed_error_median == pytest.approx(3.0)
        assert math.isnan(s.course_error_median)


class TestCues:
    """Cues are given to the munition nearest their track."""

    def test_two_cue_ids_on_one_munition_count_two(self) -> None:
        munition = TruthTarget("LM-1", "loitering_munition", "hostile", 0.0, 0.0, 0.0, 30.0)
        truth = run((munition,), (munition,))
        made = Tracks()
        made.cues = {"HO-1": (T0, 5.0, 0.0), "HO-2": (T0 + 1, 31.0, 0.0), "HO-3": (T0, 900.0, 0.0)}
        s = score(truth, made)
        assert s.cues_per_munition == {"LM-1": 2}
        assert s.unmatched_cues == 1


def test_announcements_go_to_the_nearest_hostile_target_moved_to_their_time() -> None:
    truth = run(
        (target("A", 0.0, ve=10.0), target("B", 500.0)),
        (target("A", 10.0, ve=10.0), target("B", 500.0)),
    )
    heard = [(T0 + 0.5, 5.0, 0.0), (T0 + 1.0, 490.0, 0.0), (T0 + 1.0, 505.0, 3.0), (T0, 0, 900.0)]
    per, unmatched = announcements_per_target(truth, heard, 100.0)
    assert per == {"A": 1, "B": 2}
    assert unmatched == 1


def test_percentile_interpolates() -> None:
    assert percentile([1.0, 2.0, 3.0, 4.0], 50) == pytest.approx(2.5)
    assert percentile([0.0, 10.0], 90) == pytest.approx(9.0)
    assert math.isnan(percentile([], 50))
