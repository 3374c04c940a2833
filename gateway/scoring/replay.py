"""A scenario offline: its truth, and its detections through a tracker, without the network.

``scenario_detections`` makes the Detection events the daemon would make of the simulator's
FISCHER_DETECTION frames (positions rounded to 1e-7°, confidence to a percent, the same
event ids), stamped ``start + t`` (speed 1). ``replay`` feeds them in time order to a
``Fuser`` (the fusion processor's tracker: anything with ``update`` and ``tick``) and ticks it
once a second of data time, as ``processors.fusion.FusionProcessor`` does live, then for
``linger_s`` after the last detection so lost tracks are reported.

The core never imports a plugin (tests/test_layers.py): the caller passes the fuser, e.g.
``FusionProcessor("fusion", FusionConfig()).tracker`` from bench/track_quality.py and the tests.
"""

from __future__ import annotations

import io
from collections.abc import Iterable, Iterator, Sequence
from datetime import UTC, datetime, timedelta
from typing import Protocol

from gateway.events import Detection, Position, Sensor, Track, event_id
from gateway.scoring.files import parse_truth
from gateway.scoring.model import TruthRun
from gateway.sim.scenario import Scenario
from gateway.sim.schedule import SimDetection, detections
from gateway.sim.truth import write_truth

__all__ = ["START", "Fuser", "frames", "replay", "scenario_detections", "scenario_truth"]

#: Where offline runs start: any fixed time serves.
START = datetime(2026, 6, 1, 12, 0, tzinfo=UTC)


class Fuser(Protocol):
    """What ``replay`` drives: the fusion processor's tracker."""

    def update(self, detection: Detection) -> list[Track]:
        """Fold one detection in; the Track events it causes."""
        ...

    def tick(self, now: datetime) -> list[Track]:
        """Age the tracks to ``now``; the Track events that causes."""
        ...


def _event(d: SimDetection, start: datetime) -> Detection:
    time_usec = round((start.timestamp() + d.t_s) * 1e6)
    return Detection(
        event_id=event_id(d.airframe, "det", d.detection_id, time_usec),
        airframe=d.airframe,
        time=start + timedelta(seconds=d.t_s),
        sensor=Sensor(d.sensor),
        object_class=d.object_class,
        subtype=d.subtype,
        confidence=round(d.confidence * 100) / 100.0,
        position=Position(
            lat_deg=round(d.lat_deg * 1e7) / 1e7,
            lon_deg=round(d.lon_deg * 1e7) / 1e7,
            alt_msl_m=d.alt_msl_m,
        ),
        sigma_h_m=d.sigma_h_m,
    )


def scenario_detections(scenario: Scenario, start: datetime = START) -> list[Detection]:
    """Every detection of ``scenario`` as a Detection event, in time order (ties: airframes
    in the scenario's order, as the simulator sends them)."""
    sim: list[SimDetection] = []
    for airframe in scenario.airframes:
        sim.extend(detections(scenario, airframe))
    sim.sort(key=lambda d: d.t_s)  # stable: airframe order within one instant
    return [_event(d, start) for d in sim]


def scenario_truth(scenario: Scenario, start: datetime = START) -> TruthRun:
    """The truth of ``scenario`` started at ``start`` (speed 1), as the scorer reads it."""
    out = io.StringIO()
    write_truth(out, scenario, start.timestamp())
    lines = out.getvalue().encode().splitlines(keepends=True)
    numbered: Iterator[tuple[int, bytes]] = iter(enumerate(lines, start=1))
    return parse_truth(numbered, f"{scenario.name} (truth)")


def replay(
    events: Sequence[Detection], fuser: Fuser, *, tick_s: float = 1.0, linger_s: float = 35.0
) -> list[Track]:
    """Feed ``events`` (time order) to ``fuser``, ticking every ``tick_s`` of data time and
    for ``linger_s`` after the last; every Track event it published, in order."""
    out: list[Track] = []
    if not events:
        return out
    step = timedelta(seconds=tick_s)
    next_tick = events[0].time + step
    for detection in events:
        while detection.time >= next_tick:
            out.extend(fuser.tick(next_tick))
            next_tick += step
        out.extend(fuser.update(detection))
    end = events[-1].time + timedelta(seconds=linger_s)
    while next_tick <= end:
        out.extend(fuser.tick(next_tick))
        next_tick += step
    return out


def frames(events: Iterable[Detection]) -> Iterator[list[Detection]]:
    """``events`` grouped into sensor frames: consecutive detections of one airframe and
    sensor at one time."""
    group: list[Detection] = []
    for d in events:
        if group and (d.time, d.airframe, d.sensor) != (
            group[0].time,
            group[0].airframe,
            group[0].sensor,
        ):
            yield group
            group = []
        group.append(d)
    if group:
        yield group
