"""What the scorer compares: truth frames and track reports, in one local plane.

Positions are east/north metres from one origin (the first truth position), so every
distance is Euclidean and an independent GOSPA implementation can be fed the same numbers.
Times are UNIX seconds (UTC) as the gateway stamps its events. Velocities are stored as the
gateway sees them: a run at ``speed`` 4 shows a 10 m/s tank moving at 40 m/s of UTC time,
so the scorer divides track velocities by the run's speed before comparing them with the
truth (which is in scenario metres per second).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from gateway.flow.localplane import offset_m

__all__ = ["Plane", "TrackReport", "Tracks", "TruthFrame", "TruthRun", "TruthTarget"]


@dataclass(frozen=True, slots=True)
class Plane:
    """The local tangent plane about ``origin`` (lat, lon in degrees)."""

    lat0: float
    lon0: float

    def xy(self, lat: float, lon: float) -> tuple[float, float]:
        """(east, north) metres of (lat, lon) from the origin."""
        return offset_m(self.lat0, self.lon0, lat, lon)


@dataclass(frozen=True, slots=True)
class TruthTarget:
    """One target at one truth instant."""

    target: str
    object_class: str
    affiliation: str
    x: float
    y: float
    #: Scenario metres per second (north, east).
    vn: float
    ve: float

    @property
    def speed(self) -> float:
        """Speed over ground, scenario m/s."""
        return math.hypot(self.vn, self.ve)


@dataclass(frozen=True, slots=True)
class TruthFrame:
    """Every target alive at one second of the scenario."""

    t_s: float
    unix_s: float
    targets: tuple[TruthTarget, ...]


@dataclass(frozen=True, slots=True)
class TruthRun:
    """A whole truth file: the run's frames, one per step, in time order."""

    scenario: str
    speed: float
    step_s: float
    frames: tuple[TruthFrame, ...]
    plane: Plane
    #: Every target of the scenario (also those never in range of a sensor).
    target_ids: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class TrackReport:
    """One published state of a track (a Track event)."""

    unix_s: float
    x: float
    y: float
    #: UTC metres per second as published (None: the track had no velocity).
    vn: float | None
    ve: float | None
    status: str
    object_class: str = ""


@dataclass(slots=True)
class Tracks:
    """Every track's reports in time order, and the counter-UAS cues seen."""

    reports: dict[str, list[TrackReport]] = field(default_factory=dict)
    #: handoff id → (UNIX time, x, y) of the track in its first cue.
    cues: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    #: Lines of the archive that were not readable events.
    skipped_lines: int = 0
    first_skipped_line: int | None = None

    def add(self, track_id: str, report: TrackReport) -> None:
        """Append ``report`` to ``track_id``'s history; ``sort`` once all are added."""
        self.reports.setdefault(track_id, []).append(report)

    def sort(self) -> None:
        """Put every history in time order (stable: equal times keep their arrival order)."""
        for history in self.reports.values():
            history.sort(key=lambda r: r.unix_s)
