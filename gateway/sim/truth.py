"""A scenario's ground truth: where every target is, and how fast it moves, each second.

``truth_records(scenario, start_unix_s, speed)`` yields one ``TruthRecord`` per target alive
per step (sim seconds 0, 1, ... ``duration_s``), in time order: its position as the
simulator computes it (the same ``TargetTrack.position`` the detections are drawn around)
and its velocity along its path in the scenario's own metres per second. ``utc`` is when the
gateway sees that second: ``start + t / speed``, the clock the simulator stamps detections
with (``SimulatedAirframe.unix_s``).

``write_truth`` writes them as JSON lines after a header line (``TruthHeader``); the format
is in docs/tracking.md. ``gateway.scoring`` reads it back.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from typing import TextIO

from gateway.domain.geodesy import distance_bearing
from gateway.sim.scenario import Scenario
from gateway.sim.schedule import TargetTrack, target_tracks

__all__ = [
    "TRUTH_FORMAT",
    "TruthHeader",
    "TruthRecord",
    "target_velocity",
    "truth_records",
    "write_truth",
]

#: The ``format`` of a truth file's header line.
TRUTH_FORMAT = "fischer-truth/1"
#: Every scenario target is hostile (``gateway.sim.scenario.Target``).
_AFFILIATION = "hostile"
#: Metres ahead along the path used to find the direction of travel.
_AHEAD_M = 1.0


@dataclass(frozen=True, slots=True)
class TruthHeader:
    """The first line of a truth file: which run it describes."""

    format: str
    scenario: str
    start_utc: str
    speed: float
    step_s: float
    duration_s: float
    targets: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class TruthRecord:
    """One target at one second of the scenario."""

    t_s: float
    utc: str
    target: str
    object_class: str
    subtype: str
    affiliation: str
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    north_mps: float
    east_mps: float


def _iso(unix_s: float) -> str:
    return datetime.fromtimestamp(unix_s, UTC).isoformat().replace("+00:00", "Z")


def target_velocity(track: TargetTrack, t_s: float) -> tuple[float, float]:
    """(north, east) m/s of ``track`` at ``t_s`` in scenario time: along its path at its
    speed while it moves, zero before it starts moving and once it holds at the end."""
    target = track.target
    lead_m = target.speed_mps * (t_s - target.start_s)
    along = min(lead_m, track.path.length_m) - track.offset_m
    if target.speed_mps == 0 or along < 0 or lead_m >= track.path.length_m:
        return 0.0, 0.0
    here = track.path.at(along)
    ahead = track.path.at(min(along + _AHEAD_M, track.path.length_m))
    if ahead[:2] == here[:2]:
        return 0.0, 0.0
    _, bearing = distance_bearing(here[0], here[1], ahead[0], ahead[1])
    rad = math.radians(bearing)
    return target.speed_mps * math.cos(rad), target.speed_mps * math.sin(rad)


def truth_records(
    scenario: Scenario, start_unix_s: float, speed: float = 1.0, step_s: float = 1.0
) -> Iterator[TruthRecord]:
    """Every target alive at each step from 0 to ``duration_s``, targets in scenario order."""
    tracks = target_tracks(scenario)
    steps = math.floor(scenario.duration_s / step_s + 1e-9)
    for k in range(steps + 1):
        t_s = k * step_s
        utc = _iso(start_unix_s + t_s / speed)
        for track in tracks:
            where = track.position(t_s)
            if where is None:
                continue
            north, east = target_velocity(track, t_s)
            yield TruthRecord(
                t_s=t_s,
                utc=utc,
                target=track.id,
                object_class=track.target.object_class,
                subtype=track.target.subtype,
                affiliation=_AFFILIATION,
                lat_deg=where[0],
                lon_deg=where[1],
                alt_msl_m=where[2],
                north_mps=north,
                east_mps=east,
            )


def write_truth(
    out: TextIO,
    scenario: Scenario,
    start_unix_s: float,
    speed: float = 1.0,
    step_s: float = 1.0,
    duration_s: float | None = None,
) -> int:
    """Write the header and every record of the run to ``out``; the number of records.

    ``duration_s`` cuts the run short as ``simulate --duration`` does.
    """
    if duration_s is not None and duration_s < scenario.duration_s:
        scenario = scenario.model_copy(update={"duration_s": duration_s})
    header = TruthHeader(
        format=TRUTH_FORMAT,
        scenario=scenario.name,
        start_utc=_iso(start_unix_s),
        speed=speed,
        step_s=step_s,
        duration_s=scenario.duration_s,
        targets=tuple(track.id for track in target_tracks(scenario)),
    )
    out.write(json.dumps(asdict(header)) + "\n")
    written = 0
    for record in truth_records(scenario, start_unix_s, speed, step_s):
        out.write(json.dumps(asdict(record)) + "\n")
        written += 1
    return written
