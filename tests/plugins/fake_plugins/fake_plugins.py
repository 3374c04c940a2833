"""A third-party processor, source and sink, as another package would ship them.

``Doubler`` (processor ``doubler``) consumes Detections and publishes, for each, a Track at
the same position and an event of its own type ``fake.doubled`` (an ``Extension`` it declares
in ``extension_events``): the smallest processor that shows the contract end to end. With
``misbehave`` it also publishes an undeclared type and a ``fake.doubled`` with invalid data,
which the gateway refuses and counts. ``Ticker``
(source ``ticker``) publishes one BlueForce event every ``interval_s``. ``Tally`` (sink
``tally``) appends one ``KIND EVENT_ID`` line per event to a file. They import only the public
surface: ``gateway`` and ``gateway.events``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from datetime import datetime
from typing import Any, ClassVar

import anyio
import anyio.abc
from anyio.streams.memory import MemoryObjectReceiveStream
from pydantic import BaseModel, ConfigDict, Field

from gateway import ProcessorConfig, Publish, SinkConfig, SourceConfig
from gateway.events import BlueForce, Detection, Event, EventKind, Extension, Position, Track


class DoublerConfig(ProcessorConfig):
    prefix: str = Field(default="T", description="Start of every track id.")
    misbehave: bool = Field(default=False, description="Also publish what must be refused.")


class Doubled(BaseModel):
    """A detection the doubler turned into a track."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    detection_id: str = Field(description="The detection's event_id.")
    track_id: str = Field(description="The track it became.")
    count: int = Field(ge=1, description="Detections doubled so far by this processor.")


class Doubler:
    config_model: ClassVar[type[DoublerConfig]] = DoublerConfig
    extension_events: ClassVar[dict[str, type[BaseModel]]] = {"fake.doubled": Doubled}

    def __init__(self, name: str, config: DoublerConfig) -> None:
        self.name = name
        self.config = config
        self.count = 0
        self.refused = 0

    @property
    def kinds(self) -> frozenset[EventKind]:
        return frozenset({EventKind.DETECTION})

    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Publish,
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        task_status.started()
        async with events:
            async for event in events:
                if not isinstance(event, Detection):
                    continue
                track_id = f"{self.config.prefix}-{event.airframe}-{event.object_class}"
                publish(
                    Track(
                        event_id=f"{self.config.prefix}-{event.event_id}",
                        track_id=track_id,
                        time=event.time,
                        object_class=event.object_class,
                        subtype=event.subtype,
                        confidence=event.confidence,
                        position=event.position,
                        cep50_m=event.sigma_h_m * 1.1774,
                        cep90_m=event.sigma_h_m * 2.1460,
                        airframes=(event.airframe,),
                        detection_ids=(event.event_id,),
                        first_seen=event.time,
                        last_seen=event.time,
                        hostility="hostile",
                    )
                )
                self.count += 1
                doubled = Doubled(detection_id=event.event_id, track_id=track_id, count=self.count)
                publish(self._extension("fake.doubled", event, doubled.model_dump()))
                if self.config.misbehave:
                    for type_name, data in (
                        ("fake.undeclared", {"detection_id": event.event_id}),
                        ("fake.doubled", {"detection_id": event.event_id, "count": 0}),
                    ):
                        if not publish(self._extension(type_name, event, data)):
                            self.refused += 1

    def _extension(self, type_name: str, event: Detection, data: dict[str, Any]) -> Extension:
        return Extension(
            event_id=f"{self.config.prefix}-{type_name}-{event.event_id}",
            type=type_name,
            time=event.time,
            airframe=event.airframe,
            data=data,
        )

    def status(self) -> dict[str, Any]:
        return {"doubled": self.count, "refused": self.refused}


class Misdeclared(Doubler):
    """A processor whose declaration breaks the rules: its type cannot be loaded."""

    extension_events: ClassVar[dict[str, type[BaseModel]]] = {"Doubled": Doubled}


class TickerConfig(SourceConfig):
    interval_s: float = Field(default=0.2, gt=0, description="Seconds between reports.")
    callsign: str = Field(default="TICK", description="The unit reported.")
    crash_every: int | None = Field(default=None, description="Raise after this many ticks.")


class Ticker:
    config_model: ClassVar[type[TickerConfig]] = TickerConfig

    def __init__(
        self,
        name: str,
        config: TickerConfig,
        publish: Publish,
        *,
        clock: Callable[[], datetime],
    ) -> None:
        self.name = name
        self.config = config
        self._publish = publish
        self._clock = clock
        self.sent = 0

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        task_status.started()
        while True:
            now = self._clock()
            self.sent += 1
            self._publish(
                BlueForce(
                    event_id=f"tick-{self.sent}",
                    time=now,
                    uid=self.config.callsign,
                    callsign=self.config.callsign,
                    position=Position(lat_deg=65.8, lon_deg=21.7),
                    source="ticker",
                )
            )
            if self.config.crash_every and self.sent % self.config.crash_every == 0:
                raise RuntimeError("a bug in the ticker")
            await anyio.sleep(self.config.interval_s)

    def status(self) -> dict[str, Any]:
        return {"source": self.name, "type": "ticker", "sent": self.sent}


class TallyConfig(SinkConfig):
    path: str = Field(description="The file the lines are appended to.")
    kinds: frozenset[EventKind] = Field(
        default=frozenset({EventKind.DETECTION, EventKind.TRACK, EventKind.BLUE_FORCE}),
        description="The kinds it takes.",
    )


class Tally:
    config_model: ClassVar[type[TallyConfig]] = TallyConfig

    def __init__(self, name: str, config: TallyConfig) -> None:
        self.name = name
        self.config = config
        self._file: anyio.AsyncFile[str] | None = None

    @property
    def kinds(self) -> frozenset[EventKind]:
        return self.config.kinds

    async def open(self) -> None:
        self._file = await anyio.open_file(self.config.path, "a", encoding="utf-8")

    async def send(self, batch: Sequence[Event]) -> None:
        if self._file is None:
            raise RuntimeError("not open")
        await self._file.write("".join(f"{e.kind.value} {e.event_id}\n" for e in batch))
        await self._file.flush()

    async def aclose(self) -> None:
        if self._file is not None:
            file, self._file = self._file, None
            await file.aclose()
