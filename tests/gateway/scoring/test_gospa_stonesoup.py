"""Our GOSPA against an independent implementation: Stone Soup's ``GOSPAMetric``.

The greedy tracker's picture of ``t72-column`` and of ``swarm`` (offline, as in CI) is
scored by ``gateway.scoring.score``; the very same points (truth and the tracks shown at
each second, in the scorer's plane) go to Stone Soup, which must give the same GOSPA at
every second and the same mean, to float tolerance.
"""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
from stonesoup.metricgenerator.ospametric import GOSPAMetric  # the test extra has it
from stonesoup.types.state import State

from gateway.scoring.files import tracks_from_events
from gateway.scoring.replay import replay, scenario_detections, scenario_truth
from gateway.scoring.score import ScoreSettings, picture_at, score
from gateway.sim.scenario import load_scenario
from processors.fusion import FusionConfig, FusionProcessor


@pytest.mark.parametrize("name", ["t72-column", "swarm"])
def test_gospa_per_second_agrees_with_stone_soup(name: str) -> None:
    scenario = load_scenario(name)
    truth = scenario_truth(scenario)
    published = replay(scenario_detections(scenario), FusionProcessor("f", FusionConfig()).tracker)
    tracks = tracks_from_events(published, truth.plane)
    settings = ScoreSettings()
    ours = score(truth, tracks, settings)

    times = {tid: [r.unix_s for r in history] for tid, history in tracks.reports.items()}
    measured, measured_ids, true_states, true_ids = [], [], [], []
    ours_at: dict[datetime, float] = {}
    for frame, value in zip(truth.frames, ours.gospa_per_second, strict=True):
        at = datetime.fromtimestamp(frame.unix_s, UTC)
        ours_at[at] = value
        for t in frame.targets:
            true_states.append(State([[t.x], [t.y]], timestamp=at))
            true_ids.append(t.target)
        for shown in picture_at(tracks, times, frame.unix_s, settings.max_age_s):
            measured.append(State([[shown.x], [shown.y]], timestamp=at))
            measured_ids.append(shown.track_id)
    metric = GOSPAMetric(c=settings.c_m, p=settings.p)
    result = metric.compute_over_time(measured, measured_ids, true_states, true_ids)
    theirs = {m.timestamp: float(m.value["distance"]) for m in result.value}

    assert len(theirs) > 60
    assert ours.matched_pairs > 0
    assert ours.gospa > 0
    for at, value in theirs.items():
        assert ours_at[at] == pytest.approx(value, rel=1e-9, abs=1e-9), at
    # Stone Soup skips instants with nothing on either side (GOSPA 0 there).
    assert sum(ours_at.values()) == pytest.approx(sum(theirs.values()), rel=1e-12)
