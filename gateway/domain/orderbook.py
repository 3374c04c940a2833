"""The order book: the port through which the orders processor keeps its orders durable.

The orders processor (``processors.orders``) writes one ``OrderRecord`` per order event id
each time the order moves (waiting, uploading, executing, done) and with it the status it is
about to publish; after a restart it reads them back and carries on. The spool implements
it (``gateway.spool.orderbook``) so a record joins the same group commit as the status events
the bus appends: the record is written before the status is published. ``gateway.app``
hands the book to every processor that asks for one (``KeepsOrders``); the processor never
imports the spool.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Literal, Protocol, runtime_checkable

from gateway.domain.mission import MissionStep
from gateway.events import FiveLineOrder, OrderStatus

__all__ = ["KeepsOrders", "OrderBook", "OrderRecord", "Phase"]

Phase = Literal["waiting", "uploading", "executing", "done"]
"""Where an order stands for a restart: waiting for its link (until ``deadline``), being
uploaded (the upload starts over), executing (the airframe's mission is read back), done."""


@dataclass(frozen=True, slots=True)
class OrderRecord:
    """One order as the processor keeps it (see the module docstring)."""

    order: FiveLineOrder
    digest: str
    phase: Phase
    airframe: str | None = None
    items: tuple[MissionStep, ...] = ()
    deadline: datetime | None = None
    #: The last mission item the airframe reported reached (-1: none).
    reached: int = -1
    #: The sequence number of the newest status published for the order (0: none yet).
    seq: int = 0
    #: When the record was last written, Unix seconds (set by the book).
    updated: float = 0.0


@runtime_checkable
class OrderBook(Protocol):
    """Durable order records and their statuses."""

    def save(self, record: OrderRecord, status: OrderStatus | None = None) -> None:
        """Write ``record`` (and ``status``, whose ``seq`` is the record's) in the open
        group commit. Raises ``gateway.errors.SpoolError`` when it cannot be written."""
        ...

    def load(self) -> list[OrderRecord]:
        """Every order kept, oldest first."""
        ...

    def statuses(self, order_event_id: str) -> list[OrderStatus]:
        """The statuses published for one order, by ``seq``."""
        ...


@runtime_checkable
class KeepsOrders(Protocol):
    """A processor that keeps its orders in the book: the assembly hands it over before run."""

    def keep_orders(self, book: OrderBook) -> None:
        """Take the book (before ``run``)."""
        ...
