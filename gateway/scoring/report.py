"""A ``Score`` as text for people and as JSON for tools (``fischer-gateway score``)."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from typing import Any

from gateway.scoring.score import Score

__all__ = ["score_json", "score_text"]


def _f(value: float, digits: int = 1) -> str:
    return "-" if math.isnan(value) else f"{value:.{digits}f}"


def score_text(s: Score) -> str:
    """Several lines: the headline metrics, then the tracks of each target."""
    cues = ", ".join(f"{m} {n}" for m, n in s.cues_per_munition.items()) or "no munitions"
    lines = [
        f"scenario {s.scenario}: {s.seconds} s, {s.targets} targets "
        f"({s.targets_tracked} tracked), {s.track_ids} track ids",
        f"GOSPA (mean per second) {_f(s.gospa, 2)} m  [localisation {_f(s.gospa_localisation)}, "
        f"missed {_f(s.gospa_missed)}, false {_f(s.gospa_false)}: mean squared terms]",
        f"tracks per true target {_f(s.tracks_per_target, 2)}; false tracks {s.false_tracks} "
        f"({_f(100 * s.false_track_share)} % of track ids); ID switches {s.id_switches}",
        f"position RMSE {_f(s.position_rmse_m)} m over {s.matched_pairs} matched seconds",
        f"speed error median {_f(s.speed_error_median)} m/s, p90 {_f(s.speed_error_p90)} m/s "
        f"(true speed median {_f(s.true_speed_median)} m/s); course error median "
        f"{_f(s.course_error_median)}°, p90 {_f(s.course_error_p90)}°",
        f"updates with velocity {_f(100 * s.velocity_share)} %",
        f"cues per munition: {cues}; cues matching no munition {s.unmatched_cues}",
    ]
    if s.skipped_lines:
        lines.append(f"archive lines skipped (not readable events): {s.skipped_lines}")
    for target, ids in s.tracks_of_target.items():
        lines.append(f"  {target}: {len(ids)} track(s) {' '.join(ids)}")
    return "\n".join(lines)


def _clean(value: Any) -> Any:
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_clean(v) for v in value]
    return value


def score_json(s: Score) -> str:
    """One JSON object (NaN as null)."""
    return json.dumps(_clean(asdict(s)), sort_keys=True)
