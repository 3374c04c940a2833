"""The fusion processor: Detections in, Dempster-Shafer fused Tracks out.

``FusionProcessor`` feeds each Detection from its inbox to a ``tracking.Tracker`` and
publishes the Tracks it returns. The tracker assigns the detections of one sensor frame
jointly, so a frame is processed once it holds the ``frame_size`` its detections declare,
once its source's next frame starts or, at the latest, ``frame_wait_s`` after the inbox went
quiet. It ticks the tracker about once a second (every
``tick_s``) even when no detection arrives, so held-back updates are flushed and silent
tracks are reported lost on time. The algorithm and its rules are in ``tracking``; this
module holds only the options and the loop.
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import anyio
import anyio.abc
import structlog
from anyio.streams.memory import MemoryObjectReceiveStream
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from gateway.clock import Clock, utc_now
from gateway.events import Detection, Event, EventKind
from gateway.flow.processor import ProcessorConfig, Publish
from tracking import DEFAULT_CLASSES, OTHER, Tracker, TrackerSettings
from tracking.priors import load_priors

__all__ = ["ClassPriorOption", "FusionConfig", "FusionProcessor"]

log = structlog.get_logger(__name__)


class ClassPriorOption(BaseModel):
    """One class's motion prior (``tracking.priors``)."""

    model_config = ConfigDict(extra="forbid")

    max_speed_mps: float = Field(gt=0, le=1000, description="Plausible top speed (m/s).")
    accel_mps2: float = Field(gt=0, le=100, description="Manoeuvring acceleration σ (m/s²).")


class FusionConfig(ProcessorConfig):
    """Options of the ``fusion`` processor (``processors: - {type: fusion, options: ...}``)."""

    classes: tuple[str, ...] = Field(
        default=DEFAULT_CLASSES,
        min_length=1,
        description="The class frame; any other reported class counts as 'other'.",
    )
    hostile_classes: tuple[str, ...] = Field(
        default=("tank", "armour", "loitering_munition"),
        description="Classes reported hostile; every other class is suspect.",
    )
    gate_sigma: float = Field(
        default=4.0, gt=0, le=10, description="Association gate: Mahalanobis distance, in σ."
    )
    max_gap_s: float = Field(
        default=60.0, gt=0, le=600, description="A track silent this long takes no detection."
    )
    coast_after_s: float = Field(
        default=3.0, gt=0, le=600, description="A track without detections this long coasts."
    )
    lost_after_s: float = Field(
        default=60.0, gt=0, le=3600, description="A track without detections this long is lost."
    )
    confirm_hits: int = Field(
        default=3, ge=1, le=20, description="Detections (M) that confirm a tentative track..."
    )
    confirm_window: int = Field(
        default=5, ge=1, le=50, description="...within its first N chances (M of N)."
    )
    max_tracks: int = Field(
        default=5000, ge=1, le=1_000_000, description="Live tracks at most; more are refused."
    )
    update_interval_s: float = Field(
        default=1.0, ge=0, le=60, description="Updates of one track at most this often..."
    )
    max_sigma_m: float = Field(
        default=1000.0,
        ge=1,
        le=10_000,
        description="Detections with a σ above this (m) are refused and counted (too_vague).",
    )
    max_drift_m: float = Field(
        default=5.0,
        ge=0,
        le=10_000,
        description="...or sooner, when dead-reckoning its last update is off by more (m).",
    )
    class_priors: dict[str, ClassPriorOption] = Field(
        default_factory=dict,
        description="Per-class speed limit and manoeuvre noise, over tracking/classes.yaml.",
    )
    max_speed_mps: float | None = Field(
        default=None, gt=0, le=1000, description="Raise every class's speed limit to this."
    )
    speed_scale: float = Field(
        default=1.0,
        gt=0,
        le=100,
        description="A sim played this much faster: speed limits and the velocity threshold × "
        "this, manoeuvre noise × its cube.",
    )
    report_velocity_sigma_mps: float = Field(
        default=1.6, gt=0, le=100, description="Velocity published once σ ≤ this + 6 % speed."
    )
    merge_sigma: float = Field(
        default=3.0, gt=0, le=10, description="Two tracks this close (σ) are merge candidates."
    )
    merge_after: int = Field(
        default=2, ge=1, le=20, description="...merged after agreeing this many updates."
    )
    index: Literal["grid", "all_pairs"] = Field(
        default="grid", description="Association candidates: spatial grid, or every track."
    )
    cell_m: float = Field(
        default=2000.0, ge=10, le=100_000, description="Grid cell size (m) of the spatial index."
    )
    loitering_munition: Literal["uav_attack", "missile"] = Field(
        default="uav_attack", description="The symbol a loitering munition's SIDC uses."
    )
    frame_wait_s: float = Field(
        default=0.05,
        ge=0,
        le=5,
        description="A sensor frame not known complete is processed this long after input.",
    )
    tick_s: float = Field(
        default=1.0, gt=0, le=60, description="Seconds between ageing passes without input."
    )

    @field_validator("classes")
    @classmethod
    def _distinct(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        if len(set(value)) != len(value):
            raise ValueError("classes must not repeat")
        if OTHER in value:
            raise ValueError(f"{OTHER!r} is always in the frame; do not list it")
        return value

    @model_validator(mode="after")
    def _hostile_known(self) -> FusionConfig:
        unknown = sorted(set(self.hostile_classes) - set(self.classes))
        if unknown:
            raise ValueError(f"hostile_classes {unknown} are not in classes")
        if self.confirm_hits > self.confirm_window:
            raise ValueError("confirm_hits must not exceed confirm_window")
        return self

    def settings(self) -> TrackerSettings:
        """The tracker's parameters from these options."""
        base = load_priors()
        overrides: dict[str, object] = {}
        for name in {*base.names(), *self.class_priors}:
            given = self.class_priors.get(name)
            prior = base[name] if given is None else given
            speed = prior.max_speed_mps
            if self.max_speed_mps is not None:
                speed = max(speed, self.max_speed_mps)
            overrides[name] = {"max_speed_mps": speed, "accel_mps2": prior.accel_mps2}
        return TrackerSettings(
            classes=self.classes,
            hostile_classes=frozenset(self.hostile_classes),
            gate_sigma=self.gate_sigma,
            max_gap_s=self.max_gap_s,
            coast_after_s=self.coast_after_s,
            lost_after_s=self.lost_after_s,
            confirm_hits=self.confirm_hits,
            confirm_window=self.confirm_window,
            max_tracks=self.max_tracks,
            update_interval_s=self.update_interval_s,
            max_drift_m=self.max_drift_m,
            max_sigma_m=self.max_sigma_m,
            speed_scale=self.speed_scale,
            report_velocity_sigma_mps=self.report_velocity_sigma_mps,
            merge_sigma=self.merge_sigma,
            merge_after=self.merge_after,
            priors=load_priors(overrides),
            index=self.index,
            cell_m=self.cell_m,
            loitering_munition=self.loitering_munition,
        )


class FusionProcessor:
    """Detections to fused Tracks (``tracking``), ticked every ``tick_s``."""

    config_model: ClassVar[type[BaseModel]] = FusionConfig

    def __init__(self, name: str, config: FusionConfig, *, clock: Clock = utc_now) -> None:
        self.name = name
        self.config = config
        self.tracker = Tracker(config.settings())
        self._clock = clock
        self.log = log.bind(processor=name)

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Detections only."""
        return frozenset({EventKind.DETECTION})

    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Publish,
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Fuse detections from ``events`` and publish Tracks until the stream ends.

        Cancellation-safe: the tracker's state is consistent between any two awaits.
        """
        task_status.started()
        deadline = anyio.current_time() + self.config.tick_s
        flush_at = math.inf
        async with events:
            while True:
                wake = min(deadline, flush_at)
                with anyio.move_on_after(max(0.0, wake - anyio.current_time())):
                    try:
                        event = await events.receive()
                    except anyio.EndOfStream:
                        for track in self.tracker.flush():
                            publish(track)
                        return
                    if isinstance(event, Detection):
                        for track in self.tracker.update(event):
                            publish(track)
                        flush_at = (
                            anyio.current_time() + self.config.frame_wait_s
                            if self.tracker.holding
                            else math.inf
                        )
                now = anyio.current_time()
                if now >= flush_at:
                    flush_at = math.inf
                    for track in self.tracker.flush():
                        publish(track)
                if now >= deadline:
                    deadline = now + self.config.tick_s
                    for track in self.tracker.tick(self._clock()):
                        publish(track)

    def status(self) -> dict[str, object]:
        """The tracker's live tracks and counters."""
        counts = self.tracker.counts
        return {
            "tracks": len(self.tracker),
            "confirmed": len(self.tracker.confirmed_ids),
            "frames": counts.frames,
            "associated": counts.associated,
            "created": counts.created,
            "discarded": counts.discarded,
            "merged": counts.merged,
            "speed_prior": counts.speed_prior,
            "refused_full": counts.refused_full,
            "too_vague": counts.too_vague,
            "total_conflict": counts.total_conflict,
            "lost": counts.lost,
            "overload_refused": counts.overload_refused,
        }
