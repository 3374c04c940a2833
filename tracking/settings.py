"""The tracker's parameters and counters (``processors.fusion.FusionConfig`` validates them)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from tracking.priors import Priors, load_priors

__all__ = ["DEFAULT_CLASSES", "OTHER", "TrackerCounts", "TrackerSettings"]

#: The object classes of the FISCHER dialect (``gateway.fleet.dialect.CLASS_NAMES``).
DEFAULT_CLASSES: tuple[str, ...] = (
    "tank",
    "armour",
    "infantry_platoon",
    "uav",
    "loitering_munition",
)
#: The frame's catch-all: every class not configured maps to it.
OTHER = "other"

Index = Literal["grid", "all_pairs"]


@dataclass(frozen=True, slots=True)
class TrackerSettings:
    """A tracker's parameters; see ``docs/counter-uas.md`` (fusion) for each one's meaning."""

    classes: tuple[str, ...] = DEFAULT_CLASSES
    hostile_classes: frozenset[str] = frozenset({"tank", "armour", "loitering_munition"})
    gate_sigma: float = 4.0
    max_gap_s: float = 60.0
    coast_after_s: float = 3.0
    lost_after_s: float = 60.0
    confirm_hits: int = 3
    confirm_window: int = 5
    max_tracks: int = 5000
    update_interval_s: float = 1.0
    max_drift_m: float = 5.0
    max_sigma_m: float = 1000.0
    speed_scale: float = 1.0
    speed_prior_sigma: float = 0.2
    report_velocity_sigma_mps: float = 1.6
    merge_sigma: float = 3.0
    merge_after: int = 2
    priors: Priors = field(default_factory=load_priors)
    index: Index = "grid"
    cell_m: float = 2000.0
    loitering_munition: Literal["uav_attack", "missile"] = "uav_attack"


@dataclass(slots=True)
class TrackerCounts:
    """What the tracker did, as plain counters."""

    frames: int = 0
    associated: int = 0
    created: int = 0
    confirmed: int = 0
    discarded: int = 0
    refused_full: int = 0
    total_conflict: int = 0
    speed_prior: int = 0
    coasting: int = 0
    lost: int = 0
    merged: int = 0
    #: Detections refused because their frame used up its pair budget (``MAX_FRAME_PAIRS``).
    overload_refused: int = 0
    #: Detections refused because their σ exceeds ``max_sigma_m``.
    too_vague: int = 0
