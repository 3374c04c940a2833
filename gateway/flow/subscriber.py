"""What the bus talks to: anything that takes events of some kinds, synchronously and at once.

Sink runners (``gateway.c2.sinkrunner``) and processor runners (``gateway.flow.processors``)
are subscribers; the bus knows no more about either.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from gateway.events import Event, EventKind

__all__ = ["Subscriber"]


@runtime_checkable
class Subscriber(Protocol):
    """Takes events from the bus: ``offer_slot`` is synchronous, O(1), and never blocks."""

    name: str

    @property
    def kinds(self) -> frozenset[EventKind]:
        """The event kinds it takes."""
        ...

    @property
    def description(self) -> str:
        """How config errors name it, e.g. ``sink 'tak' (cot)``."""
        ...

    def offer_slot(self, event: Event, ingest_mono: float, slot: str | None) -> None:
        """Take ``event`` (its latest-wins ``slot``, or None for durable kinds); never raises."""
        ...
