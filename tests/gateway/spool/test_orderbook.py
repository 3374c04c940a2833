"""The spool's order book (``gateway.spool.orderbook``): its bounds and its schema version.

How the orders processor uses it across a restart: tests/processors/test_orders_restart.py.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import anyio
import anyio.lowlevel
import pytest

from gateway.domain.mission import Loiter, Waypoint
from gateway.domain.orderbook import OrderRecord
from gateway.errors import SpoolError
from gateway.events import FiveLineOrder, OrderArea, OrderState, OrderStatus, OrderTask, Position
from gateway.spool.orderbook import SpoolOrderBook
from gateway.spool.store import Spool

NOW = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)


def order(order_id: str = "O-1") -> FiveLineOrder:
    return FiveLineOrder(
        event_id=f"slb-order-{order_id}",
        order_id=order_id,
        source="brigade-slb",
        time=NOW,
        airframe="F26E-001",
        task=OrderTask.OBSERVE_POINT,
        location=OrderArea(point=Position(lat_deg=65.85, lon_deg=21.1)),
    )


def test_a_record_and_its_statuses_read_back_after_the_spool_is_opened_again(
    tmp_path: Path,
) -> None:
    one = order()
    items = (Waypoint(65.85, 21.1, 500.0), Loiter(65.85, 21.1, 500.0, 60.0, 300.0))
    spool = Spool(tmp_path / "spool.db")
    book = SpoolOrderBook(spool)
    for seq, state in enumerate((OrderState.ACCEPTED, OrderState.EXECUTING), start=1):
        status = OrderStatus(
            event_id=f"{one.event_id}-{state.value}",
            order_event_id=one.event_id,
            order_id=one.order_id,
            source=one.source,
            time=NOW,
            status=state,
            seq=seq,
        )
        record = OrderRecord(one, one.content_digest(), "executing", "F26E-001", items, seq=seq)
        book.save(record, status)
    book.save(
        OrderRecord(one, one.content_digest(), "executing", "F26E-001", items, reached=0, seq=2)
    )
    spool.close()
    spool = Spool(tmp_path / "spool.db")
    try:
        again = SpoolOrderBook(spool)
        (kept,) = again.load()
        assert kept.order == one
        assert kept.items == items
        assert (kept.phase, kept.airframe, kept.reached, kept.seq) == (
            "executing",
            "F26E-001",
            0,
            2,
        )
        assert [(s.seq, s.status) for s in again.statuses(one.event_id)] == [
            (1, OrderState.ACCEPTED),
            (2, OrderState.EXECUTING),
        ]
        assert again.find("O-1") == [one.event_id]
    finally:
        spool.close()


def test_the_order_book_keeps_at_most_max_orders_done_ones(tmp_path: Path) -> None:
    spool = Spool(tmp_path / "spool.db")
    try:
        kept = SpoolOrderBook(spool, max_orders=3)
        for n in range(6):
            one = order(order_id=f"O-{n}")
            kept.save(OrderRecord(one, one.content_digest(), "done", seq=1))
        assert kept.prune() == 3
        assert sorted(r.order.order_id for r in kept.load()) == ["O-3", "O-4", "O-5"]
    finally:
        spool.close()


def test_an_order_book_of_another_schema_is_refused_naming_it(tmp_path: Path) -> None:
    spool = Spool(tmp_path / "spool.db")
    try:
        SpoolOrderBook(spool)
        with spool.writing() as db:
            db.execute("UPDATE meta SET value='9' WHERE key='orders_schema'")
        with pytest.raises(SpoolError, match="order book schema 9"):
            SpoolOrderBook(spool)
    finally:
        spool.close()


@pytest.mark.anyio
async def test_a_record_commits_at_the_end_of_its_loop_pass_without_lingering(
    tmp_path: Path,
) -> None:
    spool = Spool(tmp_path / "spool.db")
    try:
        book = SpoolOrderBook(spool)
        one = order()
        book.save(OrderRecord(one, one.content_digest(), "waiting", seq=1))
        group = spool.open_group
        assert group is not None
        assert group.waited_on  # so the end of the pass commits it, no linger
        for _ in range(3):
            await anyio.lowlevel.checkpoint()
        assert group.committed is True
        assert not group.lingered
        assert book.failed == 0
    finally:
        spool.close()
