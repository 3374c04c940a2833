"""One track: its filter, its life stage, its class evidence and what it last published.

**Kinematics.** A constant-velocity Kalman filter (``tracking.kalman``) in the east/north
plane about an anchor: the position the track had at its last update. Each update moves the
anchor to the new estimate (``offset_m``/``displace``), so the plane is always local.

**Class** evidence keeps the newest mass function of each source (airframe, sensor) and
combines the sources with Dempster's rule (``gateway.domain.evidence``): a repeated report from
one source replaces its predecessor, so one sensor alone never drives belief to 1.

**Life.** ``tentative`` until it has ``confirm_hits`` detections within its first
``confirm_window`` chances (a chance: a frame from a source that has seen it, which assigned
it a detection or not); then ``confirmed``; ``coasting`` while no detection has come for a
while; deleted when it can no longer be confirmed or has been silent too long.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from typing import Literal

from gateway.domain.evidence import MassFunction, combine
from gateway.events import MAX_TRACK_NODES, Sensor
from gateway.flow.localplane import displace, offset_m
from tracking.kalman import POSITION, Estimate, Innovation

__all__ = ["Source", "Stage", "TrackState", "fuse_sources"]

Source = tuple[str, Sensor]
"""Where a detection comes from: (airframe, sensor)."""

Stage = Literal["tentative", "confirmed", "coasting"]

#: A σ below this (m) is taken as this: a zero σ would make the filter's S singular, and no
#: airborne EO/IR/RF fix places a ground object to centimetres (a claim that fine, honest or
#: crafted, would make one detection outweigh a track's whole history).
MIN_SIGMA_M = 1.0


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
    serial: int
    lat_deg: float
    lon_deg: float
    estimate: Estimate
    updated_s: float
    first_seen: datetime
    last_seen: datetime
    sources: dict[Source, MassFunction]
    classes: MassFunction
    object_class: str
    confidence: float
    class_conflict: float = 0.0
    stage: Stage = "tentative"
    hits: int = 1
    chances: int = 1
    seen_by: set[Source] = field(default_factory=set)
    alt_msl_m: float | None = None
    subtypes: dict[str, str] = field(default_factory=dict)
    detection_ids: deque[str] = field(default_factory=lambda: deque(maxlen=32))
    detection_count: int = 0
    airframes: set[str] = field(default_factory=set)
    #: The other nodes whose detections contributed (``Detection.origin_node``), the first
    #: ``MAX_TRACK_NODES`` heard (``add_nodes``).
    nodes: set[str] = field(default_factory=set)
    sensors: set[Sensor] = field(default_factory=set)
    sequence: int = 0
    emitted_s: float = -math.inf
    emitted_class: str = ""
    published: datetime | None = None
    reach_m: float = math.inf
    #: The filter's process noise as a multiple of its class's (``Tracker`` adapts it to the
    #: track's recent normalised innovations) and their running mean (2 when the model fits).
    q_scale: float = 1.0
    nis: float = 2.0
    #: What receivers were last shown: (lat, lon, v_east, v_north, UNIX time), from which they
    #: dead-reckon until the next event (``Tracker`` publishes early when that drifts).
    shown: tuple[float, float, float, float, float] | None = None

    def add_nodes(self, nodes: set[str] | frozenset[str]) -> None:
        """Take other nodes as contributors, up to ``MAX_TRACK_NODES`` in all."""
        for node in sorted(nodes - self.nodes):
            if len(self.nodes) >= MAX_TRACK_NODES:
                return
            self.nodes.add(node)

    def predicted(self, at_s: float, q: float) -> Estimate:
        """The filter carried to ``at_s`` (never backwards)."""
        return self.estimate.predicted(at_s - self.updated_s, q)

    def innovation(self, predicted: Estimate, lat: float, lon: float, sigma_m: float) -> Innovation:
        """A measured position (σ per axis ``sigma_m``) against ``predicted``."""
        east, north = offset_m(self.lat_deg, self.lon_deg, lat, lon)
        return self.offset_innovation(predicted, east, north, sigma_m)

    @staticmethod
    def offset_innovation(
        predicted: Estimate, east: float, north: float, sigma_m: float
    ) -> Innovation:
        """As ``innovation``, the position given as (east, north) m from the anchor."""
        r = max(sigma_m, MIN_SIGMA_M) ** 2
        return predicted.innovation(east, north, r, 0.0, r, POSITION)

    def adopt(self, estimate: Estimate, at_s: float) -> None:
        """Take ``estimate`` (relative to the current anchor) as of ``at_s``; re-anchor."""
        east, north = estimate.x[0], estimate.x[1]
        self.lat_deg, self.lon_deg = displace(self.lat_deg, self.lon_deg, east, north)
        estimate.shift(east, north)
        self.estimate = estimate
        self.updated_s = max(self.updated_s, at_s)

    def set_classes(
        self, sources: dict[Source, MassFunction], masses: MassFunction, k: float
    ) -> None:
        """Adopt the sources and their combination (from ``fuse_sources``)."""
        self.sources = sources
        self.classes = masses
        self.class_conflict = k
        best, belief = masses.best()
        self.object_class, self.confidence = best, min(1.0, max(0.0, belief))

    @property
    def sigma_m(self) -> float:
        """Per-axis position σ (m), from the mean of the position variances."""
        return math.sqrt(max(self.estimate.position_var, 0.0))

    @property
    def velocity(self) -> tuple[float, float]:
        """(east, north) m/s."""
        return self.estimate.x[2], self.estimate.x[3]

    @property
    def speed_mps(self) -> float:
        """Speed over ground (m/s)."""
        return math.hypot(*self.velocity)

    @property
    def course_deg(self) -> float:
        """Course over ground, degrees clockwise from true north in [0, 360)."""
        east, north = self.velocity
        course = math.degrees(math.atan2(east, north)) % 360.0
        return 0.0 if course >= 360.0 else course
