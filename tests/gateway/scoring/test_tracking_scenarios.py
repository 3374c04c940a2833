"""Every shipped scenario offline through the fusion processor's tracker, scored against truth.

This is the CI half of issue #22's acceptance (the through-``run`` half at speeds 1 and 4 is
``python bench/track_quality.py --run``). The simulator's truth and the detections it would send
go through ``FusionProcessor("fusion", FusionConfig()).tracker`` (the shipped options), and
``gateway.scoring.score`` measures the picture against the issue's rules.
"""

from __future__ import annotations

import math

import pytest

from gateway.scoring.files import tracks_from_events
from gateway.scoring.replay import replay, scenario_detections, scenario_truth
from gateway.scoring.score import Score, score
from gateway.sim.scenario import load_scenario, shipped_scenarios
from processors.fusion import FusionConfig, FusionProcessor

#: The issue's rules: at most 1.1 tracks per true target, at most 2 % false track ids,
#: speed error p90 at most 2 m/s + 10 % of the true speed, velocity on 90 % of updates.
MAX_TRACKS_PER_TARGET = 1.1
MAX_FALSE_SHARE = 0.02
SPEED_P90_BASE_MPS, SPEED_P90_SHARE = 2.0, 0.10
MIN_VELOCITY_SHARE = 0.90


@pytest.fixture(scope="module")
def scores() -> dict[str, Score]:
    out = {}
    for name in shipped_scenarios():
        scenario = load_scenario(name)
        truth = scenario_truth(scenario)
        processor = FusionProcessor("fusion", FusionConfig())
        published = replay(scenario_detections(scenario), processor.tracker)
        out[name] = score(truth, tracks_from_events(published, truth.plane))
    return out


def test_every_scenario_is_scored_with_every_seen_target_tracked(scores: dict[str, Score]) -> None:
    assert len(scores) >= 8
    for name, s in scores.items():
        assert s.seconds > 0, name
        assert math.isfinite(s.gospa), name
        assert s.targets_tracked == s.targets, name  # every target is in sensor range
        assert s.matched_pairs > 0, name
        assert s.position_rmse_m < 50, name


def failures(name: str, s: Score) -> list[str]:
    """The issue's rules that ``s`` breaks."""
    broken = []
    if s.tracks_per_target > MAX_TRACKS_PER_TARGET:
        broken.append(f"{name}: {s.tracks_per_target:.2f} tracks per true target")
    if s.false_track_share > MAX_FALSE_SHARE:
        broken.append(f"{name}: {100 * s.false_track_share:.0f} % false track ids")
    limit = SPEED_P90_BASE_MPS + SPEED_P90_SHARE * s.true_speed_median
    if not s.speed_error_p90 <= limit:
        broken.append(f"{name}: speed error p90 {s.speed_error_p90:.1f} > {limit:.1f} m/s")
    if not s.velocity_share >= MIN_VELOCITY_SHARE:
        broken.append(f"{name}: velocity on {100 * s.velocity_share:.0f} % of updates")
    return broken


def test_the_picture_meets_the_issue_22_rules(scores: dict[str, Score]) -> None:
    broken = [line for name, s in scores.items() for line in failures(name, s)]
    assert broken == []


#: Further draws of each scenario's noise (the shipped seed is one draw): a split like the one
#: the speed prior once made of shared-target's tank on seed 335 shows up on some draw only.
MORE_DRAWS = 3


def test_one_track_per_target_on_other_draws_of_the_noise() -> None:
    """As many track ids as targets (at most 10 % more) and none false on each draw. (Which
    track a target's id ends on may swap on a draw where two column vehicles drive close:
    ID switches, which ``score`` counts apart, not a split picture.)"""
    broken = []
    for name in shipped_scenarios():
        base = load_scenario(name)
        for k in range(1, MORE_DRAWS + 1):
            scenario = base.model_copy(update={"seed": base.seed + k})
            truth = scenario_truth(scenario)
            processor = FusionProcessor("fusion", FusionConfig())
            published = replay(scenario_detections(scenario), processor.tracker)
            s = score(truth, tracks_from_events(published, truth.plane))
            if s.track_ids > MAX_TRACKS_PER_TARGET * s.targets or s.false_tracks:
                broken.append(
                    f"{name} seed {scenario.seed}: {s.track_ids} ids, {s.targets} targets"
                )
    assert broken == []
