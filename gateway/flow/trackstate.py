"""One track's estimate: position, velocity and class evidence, and how a detection updates it.

**Position** is fused by inverse variance in the local tangent plane about the track. Between
updates it is predicted at constant velocity and its per-axis σ grows with the time since
the update: (σ + σᵥ·Δt)² + (q·Δt)², where σᵥ is the velocity estimate's own σ (added linearly:
it was fitted to the same positions, so the errors are correlated) and q is
``process_noise_mps`` (manoeuvres). Before a velocity is known σᵥ is half of
``max_speed_mps`` (a target seen once could be moving at any plausible speed, so the second
detection of a fast target still falls inside the gate).

**Velocity** is a least-squares straight line through the newest ``velocity_window`` fused
positions against time. It is chosen over an alpha-beta filter because detections arrive
irregularly and from several airframes at once: a regression needs no gains tuned to an
update rate, copes with two reports a few milliseconds apart, and a short window still
follows a turning target. Its σ is the fit's, σ_pos/√Σ(t − t̄)² (two fixes 1 s apart with σ 8 m
give 11 m/s, which the gate must allow for), at most half of ``max_speed_mps``. Its speed is
clamped to ``max_speed_mps`` (physics, and the bound the spatial index relies on).

**Class** evidence keeps the newest mass function of each source (airframe, sensor) and
combines the sources with Dempster's rule (``gateway.domain.evidence``): a repeated report
from one source replaces its predecessor, so one sensor alone never drives belief to 1.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime

from gateway.domain.evidence import MassFunction, combine
from gateway.events import Sensor
from gateway.flow.localplane import displace, offset_m

__all__ = ["Source", "TrackState", "fuse_sources"]

Source = tuple[str, Sensor]
"""Where a piece of class evidence comes from: (airframe, sensor)."""

#: A σ below this (m) is taken as this: a zero σ would make inverse-variance weights infinite.
MIN_SIGMA_M = 0.1
#: Two fused positions closer in time than this (s) cannot give a velocity.
MIN_VELOCITY_SPAN_S = 0.05


def fuse_sources(sources: Mapping[Source, MassFunction]) -> tuple[MassFunction, float]:
    """The Dempster combination of ``sources`` (in a fixed order) and its total conflict K.

    K is the mass the whole combination lost to conflict: 1 − Π(1 − Kᵢ) over the steps.
    Raises ``TotalConflict`` when the sources exclude each other.
    """
    ordered = [sources[key] for key in sorted(sources)]
    combined = ordered[0]
    agreement = 1.0
    for mass in ordered[1:]:
        combined, conflict = combine(combined, mass)
        agreement *= 1.0 - conflict
    return combined, min(1.0, max(0.0, 1.0 - agreement))


@dataclass(slots=True)
class TrackState:
    """The mutable estimate behind one track id (owned by one ``Tracker``)."""

    track_id: str
    lat_deg: float
    lon_deg: float
    sigma_m: float
    updated_s: float
    first_seen: datetime
    last_seen: datetime
    sources: dict[Source, MassFunction]
    classes: MassFunction
    class_conflict: float
    object_class: str
    confidence: float
    alt_msl_m: float | None = None
    east_mps: float | None = None
    north_mps: float | None = None
    velocity_sigma_mps: float = 0.0
    subtypes: dict[str, str] = field(default_factory=dict)
    history: deque[tuple[float, float, float, float]] = field(default_factory=deque)
    detection_ids: deque[str] = field(default_factory=lambda: deque(maxlen=32))
    detection_count: int = 0
    airframes: set[str] = field(default_factory=set)
    sensors: set[Sensor] = field(default_factory=set)
    sequence: int = 0
    emitted_s: float = 0.0
    emitted_class: str = ""

    def predict(
        self, at_s: float, process_noise_mps: float, max_speed_mps: float
    ) -> tuple[float, float, float]:
        """Predicted (lat, lon, per-axis σ m) at ``at_s`` (never predicted backwards)."""
        dt = max(0.0, at_s - self.updated_s)
        if self.east_mps is None or self.north_mps is None:
            velocity_var = (0.5 * max_speed_mps) ** 2
            lat, lon = self.lat_deg, self.lon_deg
        else:
            velocity_var = self.velocity_sigma_mps**2
            lat, lon = displace(self.lat_deg, self.lon_deg, self.east_mps * dt, self.north_mps * dt)
        # The velocity was fitted to the fused positions, so its error and the position's are
        # correlated: their σ add linearly (the bound of full correlation), not in quadrature.
        spread = self.sigma_m + math.sqrt(velocity_var) * dt
        return lat, lon, math.sqrt(spread * spread + (process_noise_mps * dt) ** 2)

    def fuse_position(
        self,
        at_s: float,
        lat: float,
        lon: float,
        sigma_m: float,
        *,
        process_noise_mps: float,
        max_speed_mps: float,
        velocity_window: int,
    ) -> None:
        """Fold a measured position (σ ``sigma_m``) at ``at_s`` into the estimate."""
        p_lat, p_lon, p_sigma = self.predict(at_s, process_noise_mps, max_speed_mps)
        p_var, m_var = p_sigma**2, max(sigma_m, MIN_SIGMA_M) ** 2
        gain = p_var / (p_var + m_var)
        east, north = offset_m(p_lat, p_lon, lat, lon)
        self.lat_deg, self.lon_deg = displace(p_lat, p_lon, gain * east, gain * north)
        self.sigma_m = math.sqrt(p_var * m_var / (p_var + m_var))
        self.updated_s = max(self.updated_s, at_s)
        self.history.append((at_s, self.lat_deg, self.lon_deg, self.sigma_m))
        while len(self.history) > velocity_window:
            self.history.popleft()
        self._estimate_velocity(max_speed_mps)

    def _estimate_velocity(self, max_speed_mps: float) -> None:
        points = list(self.history)
        times = [t for t, _, _, _ in points]
        if len(points) < 2 or max(times) - min(times) < MIN_VELOCITY_SPAN_S:
            return
        _, lat0, lon0, _ = points[-1]
        offsets = [offset_m(lat0, lon0, lat, lon) for _, lat, lon, _ in points]
        sigma_pos = math.sqrt(sum(sigma**2 for _, _, _, sigma in points) / len(points))
        t_mean = sum(times) / len(times)
        e_mean = sum(e for e, _ in offsets) / len(offsets)
        n_mean = sum(n for _, n in offsets) / len(offsets)
        s_tt = sum((t - t_mean) ** 2 for t in times)
        if s_tt <= 0.0:
            return
        east = sum((t - t_mean) * (e - e_mean) for t, (e, _) in zip(times, offsets, strict=True))
        north = sum((t - t_mean) * (n - n_mean) for t, (_, n) in zip(times, offsets, strict=True))
        east, north = east / s_tt, north / s_tt
        speed = math.hypot(east, north)
        if speed > max_speed_mps:
            east, north = east * max_speed_mps / speed, north * max_speed_mps / speed
        self.east_mps, self.north_mps = east, north
        self.velocity_sigma_mps = min(0.5 * max_speed_mps, sigma_pos / math.sqrt(s_tt))

    def set_classes(
        self, sources: dict[Source, MassFunction], masses: MassFunction, k: float
    ) -> None:
        """Adopt the sources and their combination (from ``fuse_sources``)."""
        self.sources = sources
        self.classes = masses
        self.class_conflict = k
        self.object_class, self.confidence = masses.best()
        self.confidence = min(1.0, max(0.0, self.confidence))

    @property
    def speed_mps(self) -> float | None:
        """Speed over ground (m/s), once two fused positions give one."""
        if self.east_mps is None or self.north_mps is None:
            return None
        return math.hypot(self.east_mps, self.north_mps)

    @property
    def course_deg(self) -> float | None:
        """Course over ground, degrees clockwise from true north in [0, 360)."""
        if self.east_mps is None or self.north_mps is None:
            return None
        course = math.degrees(math.atan2(self.east_mps, self.north_mps)) % 360.0
        return 0.0 if course >= 360.0 else course
