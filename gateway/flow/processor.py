"""The processor contract: components that consume events from the bus and publish new ones.

Fusion, deconfliction and the GUTE II cue, order translation, a live map: each subscribes to
event kinds and publishes what it derives. A processor is found through the entry-point group
``fischer_gateway.processors`` and configured under ``processors:`` with its own options
model, like a sink. It gets its events from a bounded stream its runner fills
(``gateway.flow.processors``), so a slow processor never blocks ingest; what it publishes
goes back on the bus, but never to itself.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, Protocol, runtime_checkable

import anyio
import anyio.abc
from anyio.streams.memory import MemoryObjectReceiveStream
from pydantic import BaseModel, ConfigDict

from gateway.events import Event, EventKind

__all__ = ["Processor", "ProcessorClass", "ProcessorConfig", "Publish"]

Publish = Callable[[Event], bool]
"""Puts an event on the bus; True once it is held durably (in the spool for every durable sink
it is routed to, or it needs no spool), False if the spool refused it (full). A caller that can
have its input sent again (an order source, an airframe's detection) acknowledges only on True."""
"""Puts an event on the bus: synchronous, never blocks, never raises."""


class ProcessorConfig(BaseModel):
    """Base of every processor's options model: frozen, unknown keys rejected."""

    model_config = ConfigDict(frozen=True, extra="forbid")


@runtime_checkable
class Processor(Protocol):
    """Consumes events of ``kinds`` and publishes derived events.

    ``run`` reads ``events`` until it ends (shutdown) and calls ``publish`` for what it
    derives; it calls ``task_status.started()`` once ready. If it raises, its runner logs it
    and starts it again with backoff; events that arrived meanwhile wait in the stream.
    """

    name: str

    @property
    def kinds(self) -> frozenset[EventKind]:
        """The event kinds it consumes."""
        ...

    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Publish,
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Consume ``events`` and ``publish`` derived ones until the stream ends."""
        ...


@runtime_checkable
class MissesEvents(Protocol):
    """A processor that wants to know which events its full inbox dropped.

    ``missed`` is called (synchronously, on the publisher's turn) for each event the runner
    could not queue, so a processor whose state must not silently go stale (the blue-force
    picture) can mark it incomplete. It must be quick and never raise.
    """

    def missed(self, event: Event) -> None:
        """``event`` was dropped before reaching the processor."""
        ...


@runtime_checkable
class PinsUnits(Protocol):
    """A processor holding units fixed by orders (``blue_forces``) that no report may move.

    The gateway refuses a source's ``BlueForce`` under one of these uids before any sink or
    processor sees it, so a network report cannot draw a fixed unit elsewhere.
    """

    @property
    def pinned_uids(self) -> frozenset[str]:
        """The uids of the units it fixes."""
        ...


class ProcessorClass(Protocol):
    """What an entry point of ``fischer_gateway.processors`` must name."""

    config_model: ClassVar[type[BaseModel]]

    def __call__(self, name: str, config: Any) -> Processor: ...
