"""Scoring a tracker's picture against the ground truth, second by second.

**The picture at a truth instant** T holds every track with a report at or before T (1 ms
of rounding allowed) whose newest such report is not terminal (``lost`` or ``merged``) and is
at most ``max_age_s`` old; its position is that report's, moved on by the report's own
velocity to T (what the track claims about now).

**Per instant**, GOSPA (c, p, α = 2) between the truth and the picture, and the optimal
assignment under it: a truth target and a track closer than c are *matched*.

**Over the run:**

- ``gospa``: the mean over every instant of the run (also those with nothing to see);
- each track id is *labelled* with the target it was matched to most often; a track never
  matched is *false*. ``tracks_per_target`` is the mean number of labelled track ids over
  the targets that have any; ``false_tracks`` is the share of all track ids that are false;
- ``id_switches``: per target, how often its matched track id changes (gaps ignored);
- ``position_rmse_m`` over matched pairs;
- speed and course errors over the matched pairs whose report has a velocity (course only
  where the target moves at 1 m/s or more), track velocity divided by the run's speed;
- ``velocity_share``: of all non-terminal Track reports, the share carrying a velocity;
- cues: each Handoff id is given to the munition (class ``loitering_munition``) nearest its
  track at its first time, if closer than c; ``cues_per_munition`` counts distinct ids.
"""

from __future__ import annotations

import bisect
import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from gateway.scoring.gospa import gospa
from gateway.scoring.model import TrackReport, Tracks, TruthRun, TruthTarget

__all__ = [
    "Score",
    "ScoreSettings",
    "announcements_per_target",
    "nearest_target",
    "percentile",
    "picture_at",
    "score",
]

_TERMINAL = frozenset({"lost", "merged"})
_ROUNDING_S = 1e-3
#: Course is meaningless for a target slower than this (m/s).
_COURSE_MIN_MPS = 1.0
_MUNITION = "loitering_munition"


@dataclass(frozen=True, slots=True)
class ScoreSettings:
    """The metric's parameters (the issue's: c = 100 m, p = 2)."""

    c_m: float = 100.0
    p: float = 2.0
    max_age_s: float = 30.0


@dataclass(slots=True)
class Score:
    """Everything ``score`` measures; see the module docstring for the definitions."""

    scenario: str
    seconds: int
    targets: int
    targets_tracked: int
    track_ids: int
    gospa: float
    gospa_localisation: float
    gospa_missed: float
    gospa_false: float
    gospa_per_second: list[float]
    tracks_per_target: float
    false_tracks: int
    false_track_share: float
    id_switches: int
    position_rmse_m: float
    matched_pairs: int
    speed_error_median: float
    speed_error_p90: float
    course_error_median: float
    course_error_p90: float
    velocity_share: float
    true_speed_median: float
    cues_per_munition: dict[str, int] = field(default_factory=dict)
    unmatched_cues: int = 0
    tracks_of_target: dict[str, list[str]] = field(default_factory=dict)
    skipped_lines: int = 0


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (0–100) by linear interpolation; NaN when empty."""
    if not values:
        return math.nan
    ordered = sorted(values)
    rank = (len(ordered) - 1) * q / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


@dataclass(frozen=True, slots=True)
class _Shown:
    track_id: str
    x: float
    y: float
    report: TrackReport


def picture_at(
    tracks: Tracks, times: dict[str, list[float]], unix_s: float, max_age_s: float
) -> list[_Shown]:
    """The tracks on the picture at ``unix_s`` (``times``: each history's report times)."""
    shown = []
    for track_id, history in tracks.reports.items():
        i = bisect.bisect_right(times[track_id], unix_s + _ROUNDING_S) - 1
        if i < 0:
            continue
        report = history[i]
        age = unix_s - report.unix_s
        if report.status in _TERMINAL or age > max_age_s:
            continue
        x, y = report.x, report.y
        if report.vn is not None and report.ve is not None and age > 0:
            x += report.ve * age
            y += report.vn * age
        shown.append(_Shown(track_id, x, y, report))
    return shown


def _angle_deg(a: float, b: float) -> float:
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


def nearest_target(
    truth: TruthRun,
    unix_s: float,
    x: float,
    y: float,
    radius_m: float,
    classes: frozenset[str] | None = None,
) -> str | None:
    """The target (of ``classes``, any when None) nearest (x, y) at ``unix_s``, if closer
    than ``radius_m``; targets are moved from the nearest truth second by their velocity."""
    if not truth.frames:
        return None
    starts = [f.unix_s for f in truth.frames]
    k = min(bisect.bisect_left(starts, unix_s), len(starts) - 1)
    if k > 0 and abs(starts[k - 1] - unix_s) < abs(starts[k] - unix_s):
        k -= 1
    frame = truth.frames[k]
    dt = (unix_s - frame.unix_s) * truth.speed
    best: tuple[float, str] | None = None
    for t in frame.targets:
        if classes is not None and t.object_class not in classes:
            continue
        d = math.hypot(t.x + t.ve * dt - x, t.y + t.vn * dt - y)
        if d < radius_m and (best is None or d < best[0]):
            best = (d, t.target)
    return None if best is None else best[1]


def _cues(tracks: Tracks, truth: TruthRun, c_m: float) -> tuple[dict[str, int], int]:
    munitions = sorted(
        {t.target for f in truth.frames for t in f.targets if t.object_class == _MUNITION}
    )
    per: dict[str, set[str]] = {m: set() for m in munitions}
    unmatched = 0
    for handoff_id, (unix_s, x, y) in tracks.cues.items():
        found = nearest_target(truth, unix_s, x, y, c_m, frozenset({_MUNITION}))
        if found is None:
            unmatched += 1
        else:
            per[found].add(handoff_id)
    return {m: len(ids) for m, ids in per.items()}, unmatched


def announcements_per_target(
    truth: TruthRun, heard: Iterable[tuple[float, float, float]], radius_m: float
) -> tuple[dict[str, int], int]:
    """Count announcements (UNIX time heard, x, y) per hostile target: each goes to the
    hostile target nearest it within ``radius_m``; also how many matched none. For the
    Ra 180 net's "new target" messages, which are not archive events."""
    hostile = sorted(
        {t.target for f in truth.frames for t in f.targets if t.affiliation == "hostile"}
    )
    per = dict.fromkeys(hostile, 0)
    unmatched = 0
    for unix_s, x, y in heard:
        found = nearest_target(truth, unix_s, x, y, radius_m)
        if found is None or found not in per:
            unmatched += 1
        else:
            per[found] += 1
    return per, unmatched


def score(truth: TruthRun, tracks: Tracks, settings: ScoreSettings | None = None) -> Score:
    """Score ``tracks`` against ``truth``; see the module docstring."""
    s = settings or ScoreSettings()
    times = {tid: [r.unix_s for r in history] for tid, history in tracks.reports.items()}
    per_second: list[float] = []
    parts = [0.0, 0.0, 0.0]
    matches: dict[str, Counter[str]] = {}
    last_of_target: dict[str, str] = {}
    switches = 0
    squared: list[float] = []
    speed_errors: list[float] = []
    course_errors: list[float] = []
    true_speeds: list[float] = []
    for frame in truth.frames:
        shown = picture_at(tracks, times, frame.unix_s, s.max_age_s)
        g = gospa([(t.x, t.y) for t in frame.targets], [(e.x, e.y) for e in shown], s.c_m, s.p)
        per_second.append(g.distance)
        parts[0] += g.localisation
        parts[1] += g.missed
        parts[2] += g.false
        for i, j in g.pairs:
            target, est = frame.targets[i], shown[j]
            matches.setdefault(est.track_id, Counter())[target.target] += 1
            previous = last_of_target.get(target.target)
            if previous is not None and previous != est.track_id:
                switches += 1
            last_of_target[target.target] = est.track_id
            squared.append((target.x - est.x) ** 2 + (target.y - est.y) ** 2)
            _kinematics(target, est.report, truth.speed, speed_errors, course_errors)
            true_speeds.append(target.speed)
    return _summary(
        truth, tracks, s, per_second, parts, matches, switches, squared, speed_errors,
        course_errors, true_speeds,
    )  # fmt: skip


def _kinematics(
    target: TruthTarget,
    report: TrackReport,
    speed: float,
    speed_errors: list[float],
    course_errors: list[float],
) -> None:
    if report.vn is None or report.ve is None:
        return
    vn, ve = report.vn / speed, report.ve / speed
    speed_errors.append(abs(math.hypot(vn, ve) - target.speed))
    if target.speed >= _COURSE_MIN_MPS:
        course = math.degrees(math.atan2(ve, vn)) % 360.0
        true_course = math.degrees(math.atan2(target.ve, target.vn)) % 360.0
        course_errors.append(_angle_deg(course, true_course))


def _summary(
    truth: TruthRun,
    tracks: Tracks,
    s: ScoreSettings,
    per_second: list[float],
    parts: list[float],
    matches: dict[str, Counter[str]],
    switches: int,
    squared: list[float],
    speed_errors: list[float],
    course_errors: list[float],
    true_speeds: list[float],
) -> Score:
    tracks_of: dict[str, list[str]] = {}
    for track_id, counter in matches.items():
        label = max(counter.items(), key=lambda item: (item[1], item[0]))[0]
        tracks_of.setdefault(label, []).append(track_id)
    all_ids = len(tracks.reports)
    false = sum(1 for track_id in tracks.reports if track_id not in matches)
    updates = [r for h in tracks.reports.values() for r in h if r.status not in _TERMINAL]
    with_velocity = sum(1 for r in updates if r.vn is not None and r.ve is not None)
    cues, unmatched = _cues(tracks, truth, s.c_m)
    n = max(len(per_second), 1)
    return Score(
        scenario=truth.scenario,
        seconds=len(per_second),
        targets=len(truth.target_ids),
        targets_tracked=len(tracks_of),
        track_ids=all_ids,
        gospa=sum(per_second) / n,
        gospa_localisation=parts[0] / n,
        gospa_missed=parts[1] / n,
        gospa_false=parts[2] / n,
        gospa_per_second=per_second,
        tracks_per_target=(
            sum(len(ids) for ids in tracks_of.values()) / len(tracks_of) if tracks_of else math.nan
        ),
        false_tracks=false,
        false_track_share=false / all_ids if all_ids else 0.0,
        id_switches=switches,
        position_rmse_m=math.sqrt(sum(squared) / len(squared)) if squared else math.nan,
        matched_pairs=len(squared),
        speed_error_median=percentile(speed_errors, 50),
        speed_error_p90=percentile(speed_errors, 90),
        course_error_median=percentile(course_errors, 50),
        course_error_p90=percentile(course_errors, 90),
        velocity_share=with_velocity / len(updates) if updates else math.nan,
        true_speed_median=percentile(true_speeds, 50),
        cues_per_munition=cues,
        unmatched_cues=unmatched,
        tracks_of_target={k: sorted(v) for k, v in sorted(tracks_of.items())},
        skipped_lines=tracks.skipped_lines,
    )
