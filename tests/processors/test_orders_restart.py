"""The orders processor across a restart: its order book (the spool's) read back, per state.

A processor runs until an order reaches a state and is dropped (as kill -9 would, between
its writes); a new processor on the same spool carries the order on: a waiting order waits
on, an order mid-upload is uploaded again, an executing order has its mission read back and
goes on only if it is still the order's. Statuses keep their ``seq`` and the kept ones are
published again.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from datetime import timedelta
from pathlib import Path
from typing import Any

import anyio
import pytest
from test_orders import FENCE, NOW, Commander, order, telemetry

from gateway.domain.mission import Loiter, Waypoint
from gateway.events import Event, OrderState, OrderStatus
from gateway.spool.orderbook import SpoolOrderBook
from gateway.spool.store import Spool
from processors.orders import OrdersConfig, OrdersProcessor

Until = Callable[[list[OrderStatus]], bool]


async def run(
    book: SpoolOrderBook,
    commander: Commander,
    events: Sequence[Event],
    until: Until,
    *,
    later: Callable[[Commander], Sequence[Event]] | None = None,
    options: dict[str, Any] | None = None,
) -> list[OrderStatus]:
    """One life of a processor on ``book``: feed ``events``, then ``later(commander)`` once
    an executing order is running, until ``until(statuses)``; then it is dropped."""
    config = OrdersConfig.model_validate({"geofence": FENCE, **(options or {})})
    started = time.monotonic()
    processor = OrdersProcessor(
        "orders", config, clock=lambda: NOW + timedelta(seconds=time.monotonic() - started)
    )
    processor.attach(commander, None, 0.5)
    processor.keep_orders(book)
    published: list[OrderStatus] = []
    changed = anyio.Event()

    def publish(event: Event) -> bool:
        nonlocal changed
        assert isinstance(event, OrderStatus)
        published.append(event)
        changed.set()
        changed = anyio.Event()
        return True

    async def until_running() -> None:
        while not processor.status()["running"]:
            with anyio.move_on_after(0.05):
                await changed.wait()

    send, receive = anyio.create_memory_object_stream[Event](100)
    with send, receive, anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(processor.run, receive, publish)
            for event in events:
                await send.send(event)
            if later is not None:
                await until_running()
                await anyio.wait_all_tasks_blocked()
                for event in later(commander):
                    await send.send(event)
            while not until(published):
                with anyio.move_on_after(0.05):  # ``until`` may look at the commander too
                    await changed.wait()
            tg.cancel_scope.cancel()  # dropped: no goodbye, as kill -9
    return published


def reached(status: OrderState) -> Until:
    return lambda published: any(s.status is status for s in published)


def fly(c: Commander) -> list[Event]:
    c.progress("reached", 0)
    c.progress("reached", 1)
    return [telemetry(at=(65.851, 21.101))]


@pytest.fixture
def book(tmp_path: Path) -> Any:
    spool = Spool(tmp_path / "spool.db")
    try:
        yield SpoolOrderBook(spool)
    finally:
        spool.close()


def seqs(published: Sequence[OrderStatus]) -> list[tuple[int | None, str]]:
    return [(s.seq, s.status.value) for s in published]


@pytest.mark.anyio
async def test_an_executing_order_whose_mission_is_still_ours_completes(
    book: SpoolOrderBook,
) -> None:
    first = Commander()
    quick = {"time_on_task_s": 0.2}
    before = await run(
        book, first, [telemetry(), order()], reached(OrderState.EXECUTING), options=quick
    )
    assert seqs(before) == [(1, "accepted"), (2, "executing")]
    again = Commander()
    again.mission = tuple(first.uploads[-1][1])  # what the airframe still holds
    after = await run(
        book,
        again,
        [telemetry()],
        reached(OrderState.COMPLETED),
        later=fly,
    )
    # The kept statuses again (the issuer drops them by seq), then the rest, numbered on.
    assert seqs(after) == [(1, "accepted"), (2, "executing"), (3, "completed")]
    assert again.uploads == []
    assert again.commands == []
    assert [s.seq for s in book.statuses("slb-order-O-1")] == [1, 2, 3]
    (record,) = book.load()
    assert record.phase == "done"
    assert record.seq == 3
    assert record.reached == 1


@pytest.mark.anyio
async def test_an_executing_order_whose_airframe_flies_another_mission_fails(
    book: SpoolOrderBook,
) -> None:
    await run(book, Commander(), [telemetry(), order()], reached(OrderState.EXECUTING))
    again = Commander()
    again.mission = (Waypoint(65.9, 21.2, 300.0), Loiter(65.9, 21.2, 300.0, 60.0, 200.0))
    after = await run(book, again, [telemetry()], reached(OrderState.FAILED))
    failed = after[-1]
    assert failed.seq == 3
    assert failed.check == "mission"
    assert failed.reason is not None
    assert "no longer this order's" in failed.reason
    assert "item 0 is at 65.9000000" in failed.reason
    assert again.uploads == []


@pytest.mark.anyio
async def test_a_loiter_of_another_time_is_another_mission(book: SpoolOrderBook) -> None:
    first = Commander()
    await run(book, first, [telemetry(), order()], reached(OrderState.EXECUTING))
    waypoint, loiter = first.uploads[-1][1]
    assert isinstance(loiter, Loiter)
    again = Commander()
    again.mission = (waypoint, Loiter(loiter.lat_deg, loiter.lon_deg, loiter.alt_msl_m, 5.0, 300.0))
    after = await run(book, again, [telemetry()], reached(OrderState.FAILED))
    assert after[-1].reason is not None
    assert "item 1 loiters 5 s at 300 m; the order uploaded 600 s at 300 m" in after[-1].reason


@pytest.mark.anyio
async def test_an_order_killed_mid_upload_is_uploaded_again(book: SpoolOrderBook) -> None:
    stuck = Commander(upload_ok=False)

    async def never(*_args: Any, **_kw: Any) -> Any:
        await anyio.sleep_forever()

    stuck.upload_mission = never  # type: ignore[method-assign]
    before = await run(book, stuck, [telemetry(), order()], reached(OrderState.ACCEPTED))
    assert seqs(before) == [(1, "accepted")]
    (record,) = book.load()
    assert record.phase == "uploading"
    assert len(record.items) == 2
    again = Commander()
    after = await run(book, again, [telemetry()], reached(OrderState.EXECUTING))
    assert seqs(after) == [(1, "accepted"), (2, "executing")]
    assert [type(step) for step in again.uploads[0][1]] == [Waypoint, Loiter]


@pytest.mark.anyio
async def test_a_waiting_order_waits_on_and_is_taken_when_its_airframe_is_heard(
    book: SpoolOrderBook,
) -> None:
    unheard = Commander(linked=False)
    await run(book, unheard, [order()], reached(OrderState.WAITING))
    (record,) = book.load()
    assert record.phase == "waiting"
    assert record.deadline is not None
    after = await run(book, Commander(), [telemetry()], reached(OrderState.ACCEPTED))
    assert seqs(after)[:2] == [(1, "waiting"), (2, "accepted")]


@pytest.mark.anyio
async def test_a_waiting_order_is_rejected_at_its_kept_deadline_after_a_restart(
    book: SpoolOrderBook,
) -> None:
    short = order(not_after=NOW + timedelta(seconds=0.3))
    await run(book, Commander(linked=False), [short], reached(OrderState.WAITING))
    after = await run(book, Commander(linked=False), [], reached(OrderState.REJECTED))
    rejected = after[-1]
    assert (rejected.seq, rejected.check) == (2, "link")
    (record,) = book.load()
    assert record.phase == "done"


@pytest.mark.anyio
async def test_a_changed_order_after_a_restart_is_still_a_conflict(book: SpoolOrderBook) -> None:
    await run(book, Commander(), [telemetry(), order()], reached(OrderState.EXECUTING))
    changed = order(at=(65.86, 21.12))
    after = await run(
        book, Commander(), [changed], lambda p: any(s.status is OrderState.CONFLICT for s in p)
    )
    assert after[-1].seq == 3
