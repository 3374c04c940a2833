"""The delivery pass: idle runners of sinks that send without awaiting, served in one callback.

What it must keep: per-sink order (never ahead of what the runner's task holds or has in
flight), nothing sent before its spool append committed, the task's ordinary delivery for
whatever the sink could not take at once, and the same metrics.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import UTC, datetime

import anyio
import anyio.lowlevel
import pytest

from gateway.c2.deliverypass import DeliveryPass
from gateway.c2.sinkrunner import SinkRunner
from gateway.config import RouteConfig, SinkEntry
from gateway.events import Detection, Event, Position, Sensor, Telemetry
from gateway.flow.bus import Bus
from gateway.ops.instruments import Instruments
from gateway.spool.store import Spool
from gateway.testing import MemorySink, eventually

T0 = datetime(2026, 11, 27, 12, 0, tzinfo=UTC)


def detection(n: int) -> Detection:
    return Detection(
        event_id=f"det-{n}",
        airframe="F26E-001",
        time=T0,
        sensor=Sensor.EO,
        object_class="tank",
        confidence=0.9,
        position=Position(lat_deg=65.1, lon_deg=21.1),
        sigma_h_m=5.0,
    )


def telemetry(airframe: str, n: int) -> Telemetry:
    return Telemetry(
        event_id=f"{airframe}-{n}",
        airframe=airframe,
        time=T0,
        position=Position(lat_deg=65.0 + n * 1e-5, lon_deg=21.0, alt_msl_m=200.0),
    )


def entry(name: str, **kw: float) -> SinkEntry:
    values = {"send_timeout_s": 5.0, "retry_initial_s": 0.01, "retry_max_s": 0.05, **kw}
    return SinkEntry(name=name, type="memory", **values)  # type: ignore[arg-type]


class NowSink(MemorySink):
    """A memory sink that also sends without awaiting, as far as ``room`` allows.

    ``room`` None takes everything; a number takes that many events in all, then declines
    (as a full socket buffer would) until it is raised. ``send`` records where each event
    came from, and can be held (``gate``) to keep a batch in flight.
    """

    def __init__(self, name: str, spool: Spool | None = None) -> None:
        super().__init__(name)
        self.room: int | None = None
        self.explode = False
        self.now_events: list[str] = []
        self.task_events: list[str] = []
        self.gate: anyio.Event | None = None
        self.spool = spool
        self.unheld: list[str] = []

    def send_now(self, batch: Sequence[Event]) -> int:
        if self.explode:
            raise RuntimeError("send_now bug")
        group = None if self.spool is None else self.spool.open_group
        if group is not None and group.has_appends:
            self.unheld.extend(e.event_id for e in batch)  # must never happen
        take = len(batch) if self.room is None else min(self.room, len(batch))
        if self.room is not None:
            self.room -= take
        self.events.extend(batch[:take])
        self.now_events.extend(e.event_id for e in batch[:take])
        self._changed.set()  # what ``wait_for`` waits on
        self._changed = anyio.Event()
        return take

    async def send(self, batch: Sequence[Event]) -> None:
        if self.gate is not None:
            await self.gate.wait()
        await super().send(batch)
        self.task_events.extend(e.event_id for e in batch)


def ids(events: Sequence[Event]) -> list[str]:
    return [e.event_id for e in events]


@pytest.mark.anyio
async def test_five_sinks_of_one_publish_are_served_in_one_pass_without_their_tasks() -> None:
    spool = Spool()
    inst = Instruments()
    delivery = DeliveryPass()
    sinks = {f"s{i}": NowSink(f"s{i}", spool) for i in range(5)}
    runners = {
        name: SinkRunner(entry(name), sink, inst, spool=spool, delivery=delivery)
        for name, sink in sinks.items()
    }
    bus = Bus([RouteConfig(sinks=tuple(sinks))], runners, inst, spool=spool)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            for runner in runners.values():
                await tg.start(runner.run)
            await eventually(lambda: all(r.state == "open" for r in runners.values()))
            await anyio.lowlevel.checkpoint()  # every task parked idle
            passes = delivery.passes
            for n in range(20):
                bus.publish(detection(n))
                bus.publish(telemetry("A", n))
                await anyio.lowlevel.checkpoint()  # one loop pass per publish
            await eventually(lambda: all(len(s.events) == 40 for s in sinks.values()))
            await eventually(lambda: spool.pending_count("s0") == 0)
            tg.cancel_scope.cancel()
    expected = [i for n in range(20) for i in (f"det-{n}", f"A-{n}")]
    for name, sink in sinks.items():
        assert sorted(ids(sink.events)) == sorted(expected)
        assert [i for i in ids(sink.events) if i.startswith("det")] == [
            f"det-{n}" for n in range(20)
        ]
        assert sink.task_events == []  # the runner's task never sent a thing
        assert sink.unheld == []  # nothing sent before its append committed
        assert runners[name].sent_in_pass == 40
        assert inst.sink_sent.labels(name).value == 40
        assert inst.sink_latency.labels(name).count == 40
    assert delivery.passes - passes == 20  # one delivery pass per loop pass, for all five


@pytest.mark.anyio
async def test_a_batch_in_flight_is_never_overtaken() -> None:
    spool = Spool()
    inst = Instruments()
    sink = NowSink("s", spool)
    runner = SinkRunner(entry("s"), sink, inst, spool=spool)
    bus = Bus([RouteConfig(sinks=("s",))], {"s": runner}, inst, spool=spool)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(runner.run)
            await eventually(lambda: runner.state == "open")
            sink.room = 0  # the fast path declines: the task sends det-0..2 and holds them
            sink.gate = anyio.Event()
            for n in range(3):
                bus.publish(detection(n))
            await eventually(lambda: runner.outbox.owed == 3 and len(runner.outbox) == 0)
            sink.room = None  # from now on the fast path would take anything
            for n in range(3, 10):
                bus.publish(detection(n))
                await anyio.lowlevel.checkpoint()
            assert sink.now_events == []  # the task is not idle: the pass leaves it alone
            sink.gate.set()
            sink.gate = None
            await sink.wait_for(10)
            for n in range(10, 15):
                bus.publish(detection(n))
                await anyio.lowlevel.checkpoint()
            await sink.wait_for(15)
            tg.cancel_scope.cancel()
    assert ids(sink.events) == [f"det-{n}" for n in range(15)]
    assert sink.task_events[:3] == ["det-0", "det-1", "det-2"]
    assert sink.now_events  # served by the pass again once idle
    assert inst.sink_sent.labels("s").value == 15


@pytest.mark.anyio
async def test_what_the_sink_cannot_take_at_once_goes_to_the_task_in_order() -> None:
    spool = Spool()
    inst = Instruments()
    sink = NowSink("s", spool)
    runner = SinkRunner(entry("s"), sink, inst, spool=spool)
    bus = Bus([RouteConfig(sinks=("s",))], {"s": runner}, inst, spool=spool)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(runner.run)
            await eventually(lambda: runner.state == "open")
            await anyio.lowlevel.checkpoint()
            sink.room = 3  # room for three datagrams, then the buffer is full
            for n in range(8):
                bus.publish(detection(n))  # one pass: one batch of eight
            await sink.wait_for(8)
            await eventually(lambda: spool.pending_count("s") == 0)
            tg.cancel_scope.cancel()
    assert ids(sink.events) == [f"det-{n}" for n in range(8)]  # each once, in order
    assert sink.now_events == ["det-0", "det-1", "det-2"]
    assert sink.task_events == [f"det-{n}" for n in range(3, 8)]
    assert runner.sent_in_pass == 3
    assert inst.sink_sent.labels("s").value == 8


@pytest.mark.anyio
async def test_a_failing_send_now_falls_back_to_the_tasks_retries() -> None:
    inst = Instruments()
    sink = NowSink("s")
    runner = SinkRunner(entry("s"), sink, inst)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(runner.run)
            await eventually(lambda: runner.state == "open")
            await anyio.lowlevel.checkpoint()
            sink.explode = True
            sink.fail_transient = True  # and the task's send fails too, for a while
            for n in range(4):
                runner.offer(detection(n), 0.0)
            await eventually(lambda: inst.sink_failed.labels("s", "transient").value >= 2)
            sink.fail_transient = False
            await sink.wait_for(4)
            sink.explode = False
            await eventually(lambda: runner.failures_in_row == 0)
            runner.offer(detection(4), 0.0)
            await sink.wait_for(5)
            tg.cancel_scope.cancel()
    assert ids(sink.events) == [f"det-{n}" for n in range(5)]
    assert sink.task_events == [f"det-{n}" for n in range(4)]
    assert sink.now_events == ["det-4"]  # the circuit closed again: the pass serves it


def test_without_a_loop_the_pass_declines() -> None:
    assert not DeliveryPass().ready(SinkRunner(entry("s"), NowSink("s"), Instruments()))


class Counting:
    name = "counting"

    def __init__(self, fail: bool = False) -> None:
        self.served = 0
        self.woken = 0
        self.fail = fail

    def deliver_now(self) -> None:
        self.served += 1
        if self.fail:
            raise RuntimeError("bug in the pass")

    def wake(self) -> None:
        self.woken += 1


def test_a_pass_left_behind_by_an_ended_loop_does_not_stop_the_next_loops() -> None:
    delivery = DeliveryPass()
    runner = Counting()

    async def offer_and_leave() -> None:
        assert delivery.ready(runner)  # the loop ends before its pass runs

    async def offer_and_wait() -> None:
        assert delivery.ready(runner)
        await anyio.lowlevel.checkpoint()

    for _ in range(3):
        anyio.run(offer_and_leave)
        served = runner.served
        anyio.run(offer_and_wait)
        assert runner.served == served + 1


def test_a_runner_failing_in_the_pass_is_woken_and_the_others_served() -> None:
    delivery = DeliveryPass()
    bad, good = Counting(fail=True), Counting()

    async def main() -> None:
        delivery.ready(bad)
        delivery.ready(good)
        await anyio.lowlevel.checkpoint()

    anyio.run(main)
    assert (bad.served, bad.woken, good.served, good.woken) == (1, 1, 1, 0)
    assert delivery.passes == 1


class AsyncNowSink(MemorySink):
    """A plugin's mistake: ``send_now`` written as a coroutine."""

    async def send_now(self, batch: Sequence[Event]) -> int:
        raise AssertionError("never called: the runner does not serve it in the pass")


@pytest.mark.anyio
async def test_an_async_send_now_is_ignored_and_the_task_delivers() -> None:
    """Called without an await it would make a coroutine (and a warning) per pass."""
    spool = Spool()
    inst = Instruments()
    delivery = DeliveryPass()
    sink = AsyncNowSink("s")
    runner = SinkRunner(entry("s"), sink, inst, spool=spool, delivery=delivery)
    bus = Bus([RouteConfig(sinks=("s",))], {"s": runner}, inst, spool=spool)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(runner.run)
            await eventually(lambda: runner.state == "open")
            for n in range(3):
                bus.publish(detection(n))
                await anyio.lowlevel.checkpoint()
            await eventually(lambda: len(sink.events) == 3)
            tg.cancel_scope.cancel()
    assert ids(sink.events) == ["det-0", "det-1", "det-2"]
    assert runner.sent_in_pass == 0
