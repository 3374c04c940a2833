"""Offline replay of a shipped scenario through a tracker, scored against the scenario's truth.

The scenario's detections (``gateway.sim.schedule``: the same noise the simulator sends) become
``Detection`` events at sim time from a fixed epoch; the truth is each target's position on
its path (``TargetTrack.position``) and its velocity from a 0.2 s central difference. Each
published track event is matched to the nearest true target at its time (within 150 m).
A helper for tests and for ``bench``; not the formal scorer (``bench/track_quality.py``).
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

from gateway.events import Detection, Position, Sensor, Track
from gateway.flow.localplane import offset_m
from gateway.sim.scenario import load_scenario
from gateway.sim.schedule import SimDetection, TargetTrack, detections, target_tracks

__all__ = ["Score", "replay", "scenario_detections", "score"]

EPOCH = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
_MATCH_M = 150.0


def scenario_detections(name: str) -> tuple[list[Detection], list[TargetTrack]]:
    """Every detection of scenario ``name`` in time order, and its true targets."""
    scenario = load_scenario(name)
    sims: list[SimDetection] = sorted(
        (d for a in scenario.airframes for d in detections(scenario, a)),
        key=lambda d: (d.t_s, d.airframe, d.detection_id),
    )
    out = [
        Detection(
            event_id=f"{d.airframe}-{d.detection_id}",
            airframe=d.airframe,
            time=EPOCH + timedelta(seconds=d.t_s),
            sensor=Sensor(d.sensor),
            object_class=d.object_class,
            subtype=d.subtype,
            confidence=d.confidence,
            position=Position(lat_deg=d.lat_deg, lon_deg=d.lon_deg, alt_msl_m=d.alt_msl_m),
            sigma_h_m=d.sigma_h_m,
        )
        for d in sims
    ]
    return out, target_tracks(scenario)


def replay(
    stream: Iterable[Detection],
    update: Callable[[Detection], list[Track]],
    tick: Callable[[datetime], list[Track]],
) -> list[Track]:
    """Feed ``stream``, ticking once per second of data time; every event published."""
    out: list[Track] = []
    next_tick: datetime | None = None
    last: datetime | None = None
    for detection in stream:
        if next_tick is None:
            next_tick = detection.time + timedelta(seconds=1)
        while detection.time >= next_tick:
            out += tick(next_tick)
            next_tick += timedelta(seconds=1)
        out += update(detection)
        last = detection.time
    if last is not None:
        out += tick(last + timedelta(seconds=1))
    return out


@dataclass
class Score:
    """Tracks per true target, speed errors and how often a velocity was published."""

    targets: int
    track_ids: int
    unmatched_ids: int
    speed_errors: list[float] = field(default_factory=list)
    allowances: list[float] = field(default_factory=list)
    with_velocity: int = 0
    updates: int = 0

    @property
    def tracks_per_target(self) -> float:
        return self.track_ids / max(1, self.targets)

    @property
    def speed_p90(self) -> float:
        return _p90(self.speed_errors)

    @property
    def excess_p90(self) -> float:
        """p90 of (speed error − (2 m/s + 10 % of the true speed)): ≤ 0 meets the bar."""
        return _p90([e - a for e, a in zip(self.speed_errors, self.allowances, strict=True)])

    @property
    def velocity_share(self) -> float:
        return self.with_velocity / max(1, self.updates)


def _p90(values: list[float]) -> float:
    if not values:
        return math.nan
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, math.ceil(0.9 * len(ordered)) - 1)]


def _truth(target: TargetTrack, t_s: float) -> tuple[float, float, float, float] | None:
    here = target.position(t_s)
    before, after = target.position(t_s - 0.1), target.position(t_s + 0.1)
    if here is None or before is None or after is None:
        return None
    east, north = offset_m(before[0], before[1], after[0], after[1])
    return here[0], here[1], east / 0.2, north / 0.2


def score(events: list[Track], targets: list[TargetTrack], stream: list[Detection]) -> Score:
    """Match each live event to the nearest true target at its time; count and measure."""
    seen = {d.event_id.split("-")[0] for d in stream}  # noqa: F841 (kept for clarity)
    owners: dict[str, Counter[str]] = defaultdict(Counter)
    result = Score(targets=0, track_ids=0, unmatched_ids=0)
    for event in events:
        if event.status in ("lost", "merged"):
            continue
        t_s = (event.last_seen - EPOCH).total_seconds()
        best: tuple[float, str, tuple[float, float, float, float]] | None = None
        for target in targets:
            truth = _truth(target, t_s)
            if truth is None:
                continue
            east, north = offset_m(truth[0], truth[1], event.position.lat_deg,
                                   event.position.lon_deg)  # fmt: skip
            distance = math.hypot(east, north)
            if distance <= _MATCH_M and (best is None or distance < best[0]):
                best = (distance, target.id, truth)
        owners[event.track_id][best[1] if best else ""] += 1
        if best is None:
            continue
        result.updates += 1
        if event.speed_mps is None:
            continue
        result.with_velocity += 1
        true_speed = math.hypot(best[2][2], best[2][3])
        result.speed_errors.append(abs(event.speed_mps - true_speed))
        result.allowances.append(2.0 + 0.1 * true_speed)
    majority = {track: counts.most_common(1)[0][0] for track, counts in owners.items()}
    result.track_ids = sum(1 for owner in majority.values() if owner)
    result.unmatched_ids = sum(1 for owner in majority.values() if not owner)
    result.targets = len({owner for owner in majority.values() if owner})
    return result
