"""A scenario's timeline: which detections and friendly reports are due when. No I/O, no clock.

``schedule(scenario)`` yields every ``SimDetection`` and ``BlueReport`` of the scenario in
time order (sim seconds from 0 to ``duration_s``). Each sensor of each airframe looks every
``1 / rate_hz`` seconds and reports each target it can see: a target on its path at that
time, of a class the sensor reports, within ``range_m`` (geodesic, horizontal) of the
airframe's position on its orbit (or, in a live run, where it flies: ``sensor_looks`` and
``seen_at`` answer one look at a time, at the position the caller gives). The reported
position is the target's with Gaussian noise of ``sigma_h_m`` per axis, drawn from a
generator seeded by the scenario's ``seed`` and the observation (airframe, sensor, target,
look), so the same scenario gives the same noise whatever is asked before it. Detection ids
count up from 1 per airframe, in time order.
"""

from __future__ import annotations

import bisect
import heapq
import math
import random
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from itertools import count

from gateway.domain.geodesy import destination, distance_bearing
from gateway.sim.airframe import SimulatedAirframe
from gateway.sim.scenario import (
    CLASS_IDS,
    SENSOR_IDS,
    Airframe,
    BlueForceUnit,
    Scenario,
    Target,
    Waypoint,
)

__all__ = [
    "BlueReport",
    "Path",
    "SimDetection",
    "TargetTrack",
    "airframe_position",
    "blue_reports",
    "detections",
    "events_at",
    "schedule",
    "seen_at",
    "sensor_looks",
    "target_tracks",
]

# Slot times (k / rate) and the times asked about differ by float rounding.
_EPS_S = 1e-9


@dataclass(frozen=True, slots=True)
class SimDetection:
    """One detection as an airframe's sensor reports it (FISCHER_DETECTION fields)."""

    t_s: float
    airframe: str
    sysid: int
    detection_id: int
    sensor: str
    sensor_id: int
    target: str
    object_class: str
    class_id: int
    subtype: str
    confidence: float
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    sigma_h_m: float
    true_lat_deg: float
    true_lon_deg: float


@dataclass(frozen=True, slots=True)
class BlueReport:
    """One friendly position report (a CoT ``a-f-*`` event)."""

    t_s: float
    uid: str
    callsign: str
    type: str
    lat_deg: float
    lon_deg: float
    alt_msl_m: float


class Path:
    """Waypoints joined by geodesics, with positions by distance along them."""

    def __init__(self, waypoints: Sequence[Waypoint]) -> None:
        self.waypoints = tuple(waypoints)
        self._starts = [0.0]  # distance along the path at each waypoint
        self._bearings: list[float] = []
        for a, b in zip(self.waypoints, self.waypoints[1:], strict=False):
            length, bearing = distance_bearing(a.lat_deg, a.lon_deg, b.lat_deg, b.lon_deg)
            self._starts.append(self._starts[-1] + length)
            self._bearings.append(bearing)

    @property
    def length_m(self) -> float:
        """Length along every segment, metres."""
        return self._starts[-1]

    def at(self, distance_m: float) -> tuple[float, float, float]:
        """(lat, lon, alt MSL) ``distance_m`` along the path, clamped to its ends."""
        if distance_m <= 0 or len(self.waypoints) == 1:
            w = self.waypoints[0]
            return w.lat_deg, w.lon_deg, w.alt_msl_m
        if distance_m >= self.length_m:
            w = self.waypoints[-1]
            return w.lat_deg, w.lon_deg, w.alt_msl_m
        i = bisect.bisect_right(self._starts, distance_m) - 1
        a, b = self.waypoints[i], self.waypoints[i + 1]
        along = distance_m - self._starts[i]
        lat, lon = destination(a.lat_deg, a.lon_deg, self._bearings[i], along)
        span = self._starts[i + 1] - self._starts[i]
        alt = a.alt_msl_m + (b.alt_msl_m - a.alt_msl_m) * (along / span if span > 0 else 0.0)
        return lat, lon, alt


@dataclass(frozen=True)
class TargetTrack:
    """One moving object of the scenario (a column is one per vehicle)."""

    id: str
    target: Target
    path: Path
    offset_m: float  # behind the lead, for column vehicles

    def position(self, t_s: float) -> tuple[float, float, float] | None:
        """(lat, lon, alt MSL) at sim time ``t_s``; None while it is not in the scenario."""
        t = self.target
        if t_s + _EPS_S < t.start_s:
            return None
        lead_m = t.speed_mps * (t_s - t.start_s)
        if t.at_end == "vanish" and lead_m > self.path.length_m + _EPS_S:
            return None
        along = min(lead_m, self.path.length_m) - self.offset_m
        if along < -_EPS_S:
            return None  # this vehicle has not reached the start of the path yet
        return self.path.at(along)


def target_tracks(scenario: Scenario) -> list[TargetTrack]:
    """Every moving object: a target, or each vehicle of a column (``ID-1`` leads)."""
    tracks = []
    for target in scenario.targets:
        path = Path(target.path)
        if target.column is None:
            tracks.append(TargetTrack(target.id, target, path, 0.0))
            continue
        for i in range(target.column.count):
            tracks.append(
                TargetTrack(f"{target.id}-{i + 1}", target, path, i * target.column.spacing_m)
            )
    return tracks


def airframe_position(airframe: Airframe, t_s: float) -> tuple[float, float]:
    """Where ``airframe`` is on its orbit at ``t_s``, as its telemetry reports it."""
    return _flyer(airframe).position_at(t_s)


def _flyer(airframe: Airframe) -> SimulatedAirframe:
    return SimulatedAirframe(
        airframe.sysid, airframe.profile(), phase_rad=math.radians(airframe.orbit.phase_deg)
    )


def _noisy(rng: random.Random, lat: float, lon: float, sigma_m: float) -> tuple[float, float]:
    if sigma_m == 0:
        return lat, lon
    north, east = rng.gauss(0.0, sigma_m), rng.gauss(0.0, sigma_m)
    return destination(lat, lon, math.degrees(math.atan2(east, north)), math.hypot(north, east))


def _looks(rate_hz: float, end_s: float) -> Iterator[tuple[int, float]]:
    for k in count():
        t_s = k / rate_hz
        if t_s > end_s + _EPS_S:
            return
        yield k, t_s


def sensor_looks(airframe: Airframe, end_s: float) -> Iterator[tuple[float, int, int]]:
    """Every look of every sensor of ``airframe`` up to ``end_s``: (sim time, sensor index,
    look number), in time order."""
    return heapq.merge(
        *(_sensor_looks(s, sensor.rate_hz, end_s) for s, sensor in enumerate(airframe.sensors))
    )


def _sensor_looks(s: int, rate_hz: float, end_s: float) -> Iterator[tuple[float, int, int]]:
    # A function of its own binds ``s`` per sensor: a generator expression inside the one
    # above would read ``s`` only when iterated, the last sensor's for every one.
    for k, t_s in _looks(rate_hz, end_s):
        yield t_s, s, k


def seen_at(
    scenario: Scenario,
    airframe: Airframe,
    tracks: Sequence[TargetTrack],
    look: tuple[float, int, int],
    here: tuple[float, float],
    ids: Iterator[int],
) -> Iterator[SimDetection]:
    """What one look sees from ``here`` (lat, lon); detection ids are taken from ``ids``."""
    t_s, s, k = look
    sensor = airframe.sensors[s]
    here_lat, here_lon = here
    for track in tracks:
        target = track.target
        confidence = sensor.confidence_for(target.object_class)
        where = track.position(t_s)
        if confidence is None or where is None:
            continue
        lat, lon, alt = where
        if distance_bearing(here_lat, here_lon, lat, lon)[0] > sensor.range_m:
            continue
        # Simulated sensor noise, reproducible by design: not for secrets.
        rng = random.Random(f"{scenario.seed}/{airframe.id}/{s}/{track.id}/{k}")  # noqa: S311
        seen_lat, seen_lon = _noisy(rng, lat, lon, sensor.sigma_h_m)
        yield SimDetection(
            t_s=t_s,
            airframe=airframe.id,
            sysid=airframe.sysid,
            detection_id=next(ids),
            sensor=sensor.sensor,
            sensor_id=SENSOR_IDS[sensor.sensor],
            target=track.id,
            object_class=target.object_class,
            class_id=CLASS_IDS[target.object_class],
            subtype=target.subtype,
            confidence=confidence,
            lat_deg=seen_lat,
            lon_deg=seen_lon,
            alt_msl_m=alt,
            sigma_h_m=sensor.sigma_h_m,
            true_lat_deg=lat,
            true_lon_deg=lon,
        )


def detections(
    scenario: Scenario, airframe: Airframe, end_s: float | None = None
) -> Iterator[SimDetection]:
    """The detections ``airframe`` reports, in time order, up to ``end_s`` (the scenario's
    ``duration_s`` by default), flying its orbit."""
    end = scenario.duration_s if end_s is None else end_s
    flyer = _flyer(airframe)
    tracks = target_tracks(scenario)
    ids = count(1)
    for look in sensor_looks(airframe, end):
        yield from seen_at(scenario, airframe, tracks, look, flyer.position_at(look[0]), ids)


def _unit_reports(unit: BlueForceUnit, end_s: float) -> Iterator[BlueReport]:
    path = Path(unit.waypoints())
    for _, t_s in _looks(1.0 / unit.report_interval_s, end_s):
        lat, lon, alt = path.at(unit.speed_mps * t_s)
        yield BlueReport(t_s, unit.uid, unit.callsign, unit.type, lat, lon, alt)


def blue_reports(scenario: Scenario, end_s: float | None = None) -> Iterator[BlueReport]:
    """Every friendly report, in time order (each unit from time 0, every interval)."""
    end = scenario.duration_s if end_s is None else end_s
    return heapq.merge(
        *(_unit_reports(unit, end) for unit in scenario.blue_forces), key=lambda r: r.t_s
    )


def schedule(scenario: Scenario, end_s: float | None = None) -> Iterator[SimDetection | BlueReport]:
    """Everything the scenario sends, in time order (ties: airframes, then friendly units)."""
    streams = [detections(scenario, a, end_s) for a in scenario.airframes]
    return heapq.merge(*streams, blue_reports(scenario, end_s), key=lambda e: e.t_s)


def events_at(scenario: Scenario, t_s: float) -> list[SimDetection | BlueReport]:
    """What is due at exactly sim time ``t_s`` (within float rounding)."""
    return [e for e in schedule(scenario, t_s) if abs(e.t_s - t_s) <= 1e-6]
