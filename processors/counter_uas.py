"""Processor ``counter_uas``: fused tracks to GUTE II cues, deconflicted against blue forces.

Consumes Track and BlueForce events; publishes one ``Handoff`` per qualifying track, and a
revision of it when its deconfliction or recommendation changes (see ``gateway.flow.cue``);
once at start, a BlueForce event for each friendly unit fixed in its options, so every sink
(CoT to ATAK, say) shows what deconfliction assumes.

A handoff is a cue with a recommendation: the GUTE II operator authorises any engagement.

Options (``processors: [{name: cuas, type: counter_uas, options: {...}}]``)::

    batteries:            # GUTE II batteries: id, position, effectors (names in the table)
      - {id: GUTE-1, lat_deg: 65.80, lon_deg: 21.70, effectors: [TRACKFIRE_30MM]}
    classes: [loitering_munition, uav, helicopter]
    min_confidence: 0.9   # fused belief in the class before a track is cued
    blue_forces:          # friendly units known from orders (never expire)
      - {uid: PLT-1, callsign: 1. pluton, lat_deg: 65.81, lon_deg: 21.66}
    blue_max_age_s: 300   # a reported friendly position older than this is not used
    revision_interval_s: 5  # a cue that becomes clear again is revised at most this often
    effector_table: null  # a YAML file like gateway/data/effectors.yaml; the shipped one if null
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import anyio
import anyio.abc
import structlog
from anyio.streams.memory import MemoryObjectReceiveStream
from pydantic import BaseModel, ConfigDict, Field, model_validator

from gateway.clock import utc_now
from gateway.configfile import load_model_text, read_bounded_text
from gateway.domain.effectors import EffectorTable, check_effector_table, load_effector_table
from gateway.events import BlueForce, Event, EventKind, Position, Provenance, Track, event_id
from gateway.flow.blueforce import BlueForceRegistry
from gateway.flow.cue import Battery, CueDesk
from gateway.flow.processor import ProcessorConfig, Publish
from gateway.ops.logsetup import RateLimit

__all__ = ["CounterUasConfig", "CounterUasProcessor"]

log = structlog.get_logger(__name__)

_ID = r"^[A-Za-z0-9][A-Za-z0-9_.:-]{0,63}$"
_STRICT = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class BatteryOptions(BaseModel):
    """One GUTE II battery."""

    model_config = _STRICT

    id: str = Field(pattern=_ID, description="The battery's id, as GUTE II knows it.")
    lat_deg: float = Field(ge=-90, le=90, description="Latitude, WGS 84 degrees.")
    lon_deg: float = Field(ge=-180, le=180, description="Longitude, WGS 84 degrees.")
    alt_msl_m: float | None = Field(
        default=None, ge=-500, le=9000, description="Altitude above mean sea level, metres."
    )
    effectors: tuple[str, ...] = Field(min_length=1, description="Effector names it has.")


class FixedBlueOptions(BaseModel):
    """A friendly unit whose position is known from orders, not reported."""

    model_config = _STRICT

    uid: str = Field(pattern=_ID, description="The unit's id, as its CoT uid would be.")
    callsign: str = Field(default="", max_length=64, description="The unit's callsign.")
    lat_deg: float = Field(ge=-90, le=90, description="Latitude, WGS 84 degrees.")
    lon_deg: float = Field(ge=-180, le=180, description="Longitude, WGS 84 degrees.")


class CounterUasConfig(ProcessorConfig):
    """The options of processor ``counter_uas``."""

    model_config = _STRICT

    batteries: tuple[BatteryOptions, ...] = Field(
        min_length=1, max_length=256, description="The GUTE II batteries cues may go to."
    )
    classes: tuple[str, ...] = Field(
        default=("loitering_munition", "uav", "helicopter"),
        min_length=1,
        description="Track classes cued to a battery.",
    )
    min_confidence: float = Field(
        default=0.9, ge=0.0, le=1.0, description="Fused belief in the class before a cue."
    )
    blue_forces: tuple[FixedBlueOptions, ...] = Field(
        default=(),
        max_length=10_000,
        description="Friendly units fixed by orders: never expire, announced once at start.",
    )
    blue_max_age_s: float = Field(
        default=300.0,
        gt=0,
        le=86_400,
        description="A reported friendly position older than this is not used.",
    )
    revision_interval_s: float = Field(
        default=5.0,
        ge=0,
        le=3600,
        description="Least time between revisions of a cue that become clear (or change "
        "recommendation); a cue that stops being clear is revised at once.",
    )
    effector_table: Path | None = Field(
        default=None, description="Effector table YAML; the shipped table when omitted."
    )

    @model_validator(mode="after")
    def _unique_batteries(self) -> CounterUasConfig:
        ids = [b.id for b in self.batteries]
        if len(ids) != len(set(ids)):
            raise ValueError(f"battery ids must be unique: {sorted(ids)}")
        if self.effector_table is None:  # a table of the operator's is checked when built
            known = load_effector_table().effectors
            unknown = sorted({e for b in self.batteries for e in b.effectors} - set(known))
            if unknown:
                raise ValueError(f"unknown effectors {unknown}; the table has {sorted(known)}")
        return self


class CounterUasProcessor:
    """See the module docstring."""

    config_model: ClassVar[type[BaseModel]] = CounterUasConfig

    def __init__(self, name: str, config: CounterUasConfig) -> None:
        self.name = name
        self.config = config
        source = "gateway/data/effectors.yaml"
        if config.effector_table is None:
            table = load_effector_table()
        else:
            # An operator's file: read and parsed with the config file's bounds (a regular
            # file, size, depth, aliases), errors naming its line and key.
            source = str(config.effector_table)
            text = read_bounded_text(config.effector_table)
            table = check_effector_table(load_model_text(text, source, EffectorTable), source)
        unknown = sorted({e for b in config.batteries for e in b.effectors} - set(table.effectors))
        if unknown:
            raise ValueError(f"batteries name effectors not in {source}: {unknown}")
        self.batteries = [
            Battery(
                b.id,
                Position(lat_deg=b.lat_deg, lon_deg=b.lon_deg, alt_msl_m=b.alt_msl_m),
                frozenset(b.effectors),
            )
            for b in config.batteries
        ]
        self.blue = BlueForceRegistry(utc_now, max_age_s=config.blue_max_age_s)
        now = utc_now()
        self.fixed = [
            BlueForce(
                event_id=event_id("blue", name, unit.uid),
                uid=unit.uid,
                time=now,
                callsign=unit.callsign,
                position=Position(lat_deg=unit.lat_deg, lon_deg=unit.lon_deg),
                source=f"config:{name}",
                source_name=name,
                provenance=Provenance.CONFIGURED,
            )
            for unit in config.blue_forces
        ]
        for unit in self.fixed:
            self.blue.pin(unit)
        self._log_limit = RateLimit(interval_s=1.0)
        self.desk = CueDesk(
            self.batteries,
            table,
            self.blue,
            classes=frozenset(config.classes),
            min_confidence=config.min_confidence,
            revision_interval_s=config.revision_interval_s,
        )

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Tracks to cue and friendly positions to deconflict against."""
        return frozenset({EventKind.TRACK, EventKind.BLUE_FORCE})

    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Publish,
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Cue tracks from ``events`` until the stream ends."""
        for battery in self.batteries:
            log.info(
                "battery_registered",
                processor=self.name,
                battery=battery.id,
                lat=battery.position.lat_deg,
                lon=battery.position.lon_deg,
                effectors=sorted(battery.effectors),
            )
        for unit in self.fixed:
            publish(unit)
        task_status.started()
        async with events:
            async for event in events:
                if isinstance(event, BlueForce):
                    self.blue.update(event)
                elif isinstance(event, Track):
                    handoff = self.desk.consider(event)
                    if handoff is None:
                        continue
                    # One line a second at most: a flood of spoofed tracks (an unsecured link)
                    # must not become a log line per packet; every cue is in the archive.
                    if self._log_limit.allow("handoff"):
                        log.info(
                            "handoff",
                            processor=self.name,
                            handoff=handoff.event_id,
                            revision=handoff.revision,
                            status=handoff.status,
                            battery=handoff.battery,
                            deconfliction_clear=handoff.deconfliction.clear,
                            recommended=handoff.recommended_effector,
                            handed_off=self.desk.counts.handed_off,
                        )
                    publish(handoff)

    @property
    def pinned_uids(self) -> frozenset[str]:
        """The units fixed in ``blue_forces``: no source's report may move them."""
        return frozenset(unit.uid for unit in self.fixed)

    def missed(self, event: Event) -> None:
        """A friendly report its full inbox dropped: the blue-force picture is incomplete."""
        if isinstance(event, BlueForce):
            self.blue.lost()

    def status(self) -> dict[str, Any]:
        """Counters for /status."""
        counts = self.desk.counts
        return {
            "batteries": [b.id for b in self.batteries],
            "blue_units": len(self.blue),
            "blue_picture_complete": self.blue.complete,
            "blue_dropped": self.blue.dropped,
            "handed_off": counts.handed_off,
            "revised": counts.revised,
            "not_clear": counts.not_clear,
            "out_of_reach": counts.out_of_reach,
            "below_confidence": counts.below_confidence,
            "superseded": counts.superseded,
            "carried_on": counts.carried_on,
            "withdrawn": counts.withdrawn,
        }
