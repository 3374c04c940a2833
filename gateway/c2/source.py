"""The source contract: inputs beyond the airframes that publish events onto the bus.

A source is found through the entry-point group ``fischer_gateway.sources`` and configured
under ``sources:`` (``name``, ``type`` and its own options beside them). Built in: ``cot``
(``sinks/cot/source.py``: friendly positions from ATAK/WinTAK/iTAK); NFFI, order intake and NATS
come the same way. A source binds in ``run`` and calls ``task_status.started()`` once bound;
it publishes events with the given ``publish`` (synchronous, never blocks; True once the event
is held durably, False if the spool refused it, so a source whose peer can send again
acknowledges only on True), must never raise
on bad input (count it instead), and reports itself on ``/status`` through ``status()``.
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime
from typing import Any, ClassVar, Protocol, runtime_checkable

import anyio
import anyio.abc
from pydantic import BaseModel, ConfigDict

from gateway.events import Event, EventKind, OrderStatus
from gateway.spool.group import Commit

__all__ = [
    "Commit",
    "DetectionLedger",
    "KeepsStatuses",
    "LedgerAware",
    "OrderStatusFeed",
    "OrderStatusListener",
    "OwnAirframesAware",
    "Source",
    "SourceClass",
    "SourceConfig",
    "StatusArchive",
]


class SourceConfig(BaseModel):
    """Base of every source's options model: frozen, unknown keys rejected."""

    model_config = ConfigDict(frozen=True, extra="forbid")


@runtime_checkable
class Source(Protocol):
    """A running input: bound in ``run``, described by ``status``."""

    name: str

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind, report started, and receive until cancelled."""
        ...

    def status(self) -> dict[str, object]:
        """What /status shows for this source (counts by outcome, connections ...)."""
        ...


class SourceClass(Protocol):
    """What an entry point of ``fischer_gateway.sources`` must name."""

    config_model: ClassVar[type[BaseModel]]

    def __call__(
        self,
        name: str,
        config: Any,
        publish: Callable[[Event], bool],
        *,
        clock: Callable[[], datetime],
    ) -> Source: ...


@runtime_checkable
class OrderStatusListener(Protocol):
    """A source that answers its orders' issuer with each ``OrderStatus`` (SLB, SWECCIS).

    ``on_order_status`` is called for every status on the bus, synchronously, from the bus:
    it must not block or raise. A source keeps those of its own orders (``status.source`` is
    its name) in a bounded queue and reports them from its own task.
    """

    name: str

    def on_order_status(self, status: OrderStatus) -> None:
        """Take one status (any source's); never blocks, never raises."""
        ...


class StatusArchive(Protocol):
    """The statuses kept for each order (the spool's order book, ``gateway.spool.orderbook``)."""

    def statuses(self, order_event_id: str) -> list[OrderStatus]:
        """The statuses published for one order, by ``seq``."""
        ...


@runtime_checkable
class OwnAirframesAware(Protocol):
    """A source of other nodes' airframe events (``nats``), told this node's own airframe ids.

    The assembly calls ``set_own_airframes`` once, before ``run``: another node's state of one
    of them is refused for good (counted, never on the bus), so no remote message moves an
    airframe of this node's own fleet.
    """

    name: str

    def set_own_airframes(self, airframes: frozenset[str]) -> None:
        """Refuse from now on every remote state of one of ``airframes``."""
        ...


class DetectionLedger(Protocol):
    """What a source that acknowledges its peer needs of the spool (``gateway.spool.Spool``):
    its group commit, and the detection ids taken in (kept across restarts)."""

    def group(self) -> Commit:
        """The open group commit (opened now if none is); raises if the spool cannot begin."""
        ...

    def flush(self) -> bool:
        """Commit the open group now; False if it did not commit."""
        ...

    def seen(self, event_id: str) -> bool:
        """True if this detection was taken in already (within the spool's window)."""
        ...

    def remember(self, event_id: str) -> None:
        """Record this detection as taken in, in the open group."""
        ...


@runtime_checkable
class KeepsStatuses(Protocol):
    """A source that answers questions about its orders' statuses from the archive (the
    ``local`` source: ``fischer-gateway order --status ID``)."""

    def keep_statuses(self, archive: StatusArchive) -> None:
        """Take the archive (before ``run``)."""
        ...


@runtime_checkable
class LedgerAware(Protocol):
    """A source that acknowledges its peer only once what it took is committed (``nats``).

    The assembly calls ``set_ledger`` once, before ``run``, with the spool: the source drops a
    detection whose id the spool has already taken in (across restarts, like an airframe's
    re-send) and acknowledges what it published once the group holding it has committed.
    """

    name: str

    def set_ledger(self, ledger: DetectionLedger) -> None:
        """Use ``ledger`` from now on."""
        ...


class OrderStatusFeed:
    """Subscribes ``OrderStatusListener`` sources to ``order_status`` events on the bus.

    A bus subscriber like a processor runner (``gateway.flow.subscriber.Subscriber``, matched
    by shape). The assembly makes one before the bus and adds each listening source to it.
    """

    name = "order-status-feed"
    kinds: frozenset[EventKind] = frozenset({EventKind.ORDER_STATUS})
    description = "the sources' order-status feed"

    def __init__(self) -> None:
        self.listeners: list[OrderStatusListener] = []

    def add(self, listener: OrderStatusListener) -> None:
        """Give ``listener`` every ``OrderStatus`` from now on."""
        self.listeners.append(listener)

    def offer_slot(self, event: Event, ingest_mono: float, slot: str | None) -> None:
        """Pass an ``OrderStatus`` of this node's own to every listening source (another
        node's, taken by the ``nats`` source, answers no issuer of this node)."""
        if isinstance(event, OrderStatus) and event.origin_node is None:
            for listener in self.listeners:
                listener.on_order_status(event)
