"""Runs one processor: a bounded inbox from the bus, its lifetime, restarts, metrics.

``ProcessorRunner`` is a bus ``Subscriber``: ``offer_slot`` puts the event in a bounded
memory stream without waiting (when it is full the event is dropped, counted and logged at
most every few seconds, so a slow processor never slows ingest; a processor with a ``missed``
method is told which events it lost). ``run`` starts the
processor with a clone of that stream and a ``publish`` that puts its events back on the bus
(never back to itself); if the processor raises, it is logged and started again with jittered
backoff, and what arrived meanwhile is still in the stream. The ``Extension`` events it
publishes are checked against its declared ``extension_events`` first (``gateway.flow.extensions``).
"""

from __future__ import annotations

import anyio
import anyio.abc
import structlog

from gateway.events import Event, EventKind, declared_extensions
from gateway.flow.extensions import ExtensionGate
from gateway.flow.processor import MissesEvents, Processor, Publish
from gateway.ops.instruments import Instruments
from gateway.ops.logsetup import RateLimit
from gateway.ops.pluginstatus import read_status
from gateway.ops.supervise import Supervised, supervise

__all__ = ["ProcessorRunner"]

log = structlog.get_logger(__name__)


class ProcessorRunner:
    """Owns one processor's inbox and the task that runs it."""

    def __init__(
        self,
        name: str,
        type_name: str,
        processor: Processor,
        instruments: Instruments,
        publish: Publish,
        *,
        queue_max: int,
    ) -> None:
        self.name = name
        self.type_name = type_name
        self.processor = processor
        self.kinds: frozenset[EventKind] = frozenset(processor.kinds)
        self._publish = publish
        self.extensions = ExtensionGate(name, declared_extensions(processor), instruments)
        self._send, self._receive = anyio.create_memory_object_stream[Event](queue_max)
        self._publishing = False
        self.record = Supervised(name)
        self._in = instruments.processor_events.labels(name, "in")
        self._out = instruments.processor_events.labels(name, "out")
        self._dropped = instruments.processor_events.labels(name, "dropped")
        self._log_limit = RateLimit(interval_s=5.0)
        self.log = log.bind(processor=name)

    @property
    def description(self) -> str:
        """How config errors name this processor."""
        return f"processor {self.name!r} ({self.type_name})"

    def offer_slot(self, event: Event, ingest_mono: float, slot: str | None) -> None:
        """Queue ``event`` for the processor without waiting; never raises."""
        if self._publishing:
            return  # its own output coming back round: never fed to itself
        try:
            self._send.send_nowait(event)
        except (anyio.WouldBlock, anyio.ClosedResourceError, anyio.BrokenResourceError):
            self._dropped.inc()
            if isinstance(self.processor, MissesEvents):
                self.processor.missed(event)
            if self._log_limit.allow("full"):
                self.log.error(
                    "processor_inbox_full",
                    kind=event.kind.value,
                    dropped=self._dropped.value,
                    note="the processor is slower than its input",
                )
        else:
            self._in.inc()

    def publish(self, event: Event) -> bool:
        """Put one of the processor's events on the bus; an ``Extension`` once checked.

        False (nothing published) for an extension event its processor did not declare or
        whose data its model rejects (``ExtensionGate``).
        """
        if event.kind is EventKind.EXTENSION:
            admitted = self.extensions.admit(event)
            if admitted is None:
                return False
            event = admitted
        self._publishing = True
        try:
            held = self._publish(event)
        finally:
            self._publishing = False
        self._out.inc()
        return held

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Run the processor until cancelled, restarting it when it fails."""
        try:
            await supervise(self._run_once, self.record, what="processor", task_status=task_status)
        finally:
            self.close()

    def close(self) -> None:
        """Close the inbox (the runner's task does so when it ends)."""
        self._send.close()
        self._receive.close()

    async def _run_once(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        # A fresh clone each time, closed whatever the processor did with it.
        async with self._receive.clone() as inbox:
            await self.processor.run(inbox, self.publish, task_status=task_status)

    def status(self) -> dict[str, object]:
        """State and counters for /status, and the processor's own under ``detail``."""
        own = getattr(self.processor, "status", None)
        detail = read_status(own, f"processor {self.name}") if callable(own) else None
        return {
            "processor": self.name,
            "type": self.type_name,
            "state": self.record.state,
            "reason": self.record.reason,
            "restarts": self.record.restarts,
            "events_in": int(self._in.value),
            "events_out": int(self._out.value),
            "dropped": int(self._dropped.value),
            **({"detail": detail} if detail is not None else {}),
        }
