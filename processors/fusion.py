"""The fusion processor: Detections in, Dempster-Shafer fused Tracks out.

``FusionProcessor`` feeds each Detection from its inbox to a ``gateway.flow.tracker.Tracker``
and publishes the Tracks it returns. It ticks the tracker about once a second (every
``tick_s``) even when no detection arrives, so held-back updates are flushed and silent
tracks are reported lost on time. The algorithm and its rules are in ``gateway.flow.tracker``;
this module holds only the options and the loop.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import anyio
import anyio.abc
import structlog
from anyio.streams.memory import MemoryObjectReceiveStream
from pydantic import BaseModel, Field, field_validator, model_validator

from gateway.clock import Clock, utc_now
from gateway.events import Detection, Event, EventKind
from gateway.flow.processor import ProcessorConfig, Publish
from gateway.flow.tracker import DEFAULT_CLASSES, OTHER, Tracker, TrackerSettings

__all__ = ["FusionConfig", "FusionProcessor"]

log = structlog.get_logger(__name__)


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
        default=3.0, gt=0, le=10, description="Association gate, in combined σ."
    )
    max_gap_s: float = Field(
        default=10.0, gt=0, le=600, description="A track older than this is not associated."
    )
    lost_after_s: float = Field(
        default=30.0, gt=0, le=3600, description="A track without detections this long is lost."
    )
    max_tracks: int = Field(
        default=5000, ge=1, le=1_000_000, description="Live tracks at most; more are refused."
    )
    update_interval_s: float = Field(
        default=1.0, ge=0, le=60, description="Updates of one track at most this often."
    )
    process_noise_mps: float = Field(
        default=5.0, ge=0, le=100, description="Velocity uncertainty that grows position σ."
    )
    max_speed_mps: float = Field(
        default=100.0, gt=0, le=1000, description="The fastest plausible target (m/s)."
    )
    velocity_window: int = Field(
        default=6, ge=2, le=64, description="Fused positions the velocity is fitted over."
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
        return self

    def settings(self) -> TrackerSettings:
        """The tracker's parameters from these options."""
        return TrackerSettings(
            classes=self.classes,
            hostile_classes=frozenset(self.hostile_classes),
            gate_sigma=self.gate_sigma,
            max_gap_s=self.max_gap_s,
            lost_after_s=self.lost_after_s,
            max_tracks=self.max_tracks,
            update_interval_s=self.update_interval_s,
            process_noise_mps=self.process_noise_mps,
            max_speed_mps=self.max_speed_mps,
            velocity_window=self.velocity_window,
            index=self.index,
            cell_m=self.cell_m,
            loitering_munition=self.loitering_munition,
        )


class FusionProcessor:
    """Detections to fused Tracks (``gateway.flow.tracker``), ticked every ``tick_s``."""

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
        async with events:
            while True:
                with anyio.move_on_after(max(0.0, deadline - anyio.current_time())):
                    try:
                        event = await events.receive()
                    except anyio.EndOfStream:
                        return
                    if isinstance(event, Detection):
                        for track in self.tracker.update(event):
                            publish(track)
                if anyio.current_time() >= deadline:
                    deadline = anyio.current_time() + self.config.tick_s
                    for track in self.tracker.tick(self._clock()):
                        publish(track)

    def status(self) -> dict[str, object]:
        """The tracker's live tracks and counters."""
        counts = self.tracker.counts
        return {
            "tracks": len(self.tracker),
            "associated": counts.associated,
            "created": counts.created,
            "refused_full": counts.refused_full,
            "total_conflict": counts.total_conflict,
            "lost": counts.lost,
        }
