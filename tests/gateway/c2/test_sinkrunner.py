"""SinkRunner and Bus: queue policies, retry, dead letters, isolation between sinks."""

from __future__ import annotations

import time
from datetime import UTC, datetime

import anyio
import anyio.lowlevel
import pytest

from gateway.c2.sinkrunner import SinkRunner
from gateway.config import RouteConfig, SinkEntry
from gateway.events import Detection, EventKind, Position, Sensor, Telemetry
from gateway.flow.bus import Bus
from gateway.ops.instruments import Instruments
from gateway.spool.store import Spool
from gateway.testing import MemorySink, eventually

T0 = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)


def telemetry(airframe: str, n: int) -> Telemetry:
    return Telemetry(
        event_id=f"{airframe}-{n}",
        airframe=airframe,
        time=T0,
        position=Position(lat_deg=65.0 + n * 1e-5, lon_deg=21.0, alt_msl_m=200.0),
    )


def detection(n: int, object_class: str = "tank") -> Detection:
    return Detection(
        event_id=f"det-{n}",
        airframe="F26E-001",
        time=T0,
        sensor=Sensor.EO,
        object_class=object_class,
        confidence=0.9,
        position=Position(lat_deg=65.1, lon_deg=21.1),
        sigma_h_m=5.0,
    )


def entry(name: str, **kw: float) -> SinkEntry:
    values = {"send_timeout_s": 0.2, "retry_initial_s": 0.01, "retry_max_s": 0.05, **kw}
    return SinkEntry(name=name, type="memory", **values)  # type: ignore[arg-type]


class TestPolicies:
    """What a runner keeps while its sink is not taking events."""

    def test_latest_wins_keeps_one_telemetry_per_airframe(self) -> None:
        inst = Instruments()
        runner = SinkRunner(entry("m"), MemorySink("m"), inst)
        for n in range(50):
            runner.offer(telemetry("A", n), 0.0)
            runner.offer(telemetry("B", n), 0.0)
        assert runner.depth == (2, 0)
        assert inst.sink_superseded.labels("m").value == 98

    @pytest.mark.anyio
    async def test_durable_kinds_beyond_the_window_wait_in_the_spool_in_order(self) -> None:
        inst = Instruments()
        sink = MemorySink("m")
        runner = SinkRunner(entry("m", queue_max=10, batch_max=4), sink, inst)
        for n in range(35):
            runner.offer(detection(n), 0.0)
        assert runner.depth == (0, 35)
        assert len(runner.outbox) == 10  # the rest only in the spool
        assert inst.sink_dropped.labels("m", "overflow").value == 0
        with anyio.fail_after(10):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await sink.wait_for(35)
                await eventually(lambda: runner.depth == (0, 0))
                tg.cancel_scope.cancel()
        assert [e.event_id for e in sink.events] == [f"det-{n}" for n in range(35)]
        assert runner.depth == (0, 0)

    def test_a_full_spool_refuses_and_counts_durable_events(self) -> None:
        inst = Instruments()
        spool = Spool(max_bytes=64 * 1024)
        runner = SinkRunner(entry("m", queue_max=10), MemorySink("m"), inst, spool=spool)
        for n in range(2000):
            runner.offer(detection(n), 0.0)
        refused = inst.sink_dropped.labels("m", "overflow").value
        assert refused > 0
        assert runner.depth == (0, 2000 - refused)
        assert spool.refused == refused


async def run_runners(*runners: SinkRunner, until: anyio.Event) -> None:
    async with anyio.create_task_group() as tg:
        for runner in runners:
            await tg.start(runner.run)
        await until.wait()
        tg.cancel_scope.cancel()


class TestDelivery:
    """Delivery, retry and rejection against real sink behaviour."""

    @pytest.mark.anyio
    async def test_transient_failures_are_retried_until_delivered_in_order(self) -> None:
        sink = MemorySink("m")
        sink.fail_transient = True
        inst = Instruments()
        runner = SinkRunner(entry("m"), sink, inst)
        for n in range(5):
            runner.offer(detection(n), time.monotonic())
        with anyio.fail_after(10):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: inst.sink_failed.labels("m", "transient").value >= 3)
                assert runner.state == "retrying"
                sink.fail_transient = False
                await sink.wait_for(5)
                assert runner.state == "open"
                tg.cancel_scope.cancel()
        assert [e.event_id for e in sink.events] == [f"det-{n}" for n in range(5)]
        assert inst.sink_latency.labels("m").count == 5  # type: ignore[attr-defined]

    @pytest.mark.anyio
    async def test_permanent_rejection_dead_letters_durable_events(self) -> None:
        sink = MemorySink("m")
        sink.fail_permanent = True
        inst = Instruments()
        runner = SinkRunner(entry("m"), sink, inst)
        runner.offer(detection(1), time.monotonic())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: bool(runner.dead_letters))
                tg.cancel_scope.cancel()
        assert runner.dead_letters[0][0].event_id == "det-1"
        assert inst.sink_dropped.labels("m", "rejected").value == 1

    @pytest.mark.anyio
    async def test_hung_send_times_out_and_keeps_the_events(self) -> None:
        sink = MemorySink("m")
        sink.hang = True
        inst = Instruments()
        runner = SinkRunner(entry("m", send_timeout_s=0.05), sink, inst)
        runner.offer(detection(1), time.monotonic())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: inst.sink_failed.labels("m", "timeout").value >= 2)
                sink.hang = False
                await sink.wait_for(1)
                tg.cancel_scope.cancel()
        assert [e.event_id for e in sink.events] == ["det-1"]

    @pytest.mark.anyio
    async def test_stop_drains_the_queue_then_closes_the_sink(self) -> None:
        sink = MemorySink("m")
        runner = SinkRunner(entry("m"), sink, Instruments())
        for n in range(300):
            runner.offer(detection(n), time.monotonic())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                runner.stop()
                await runner.wait_done()
        assert len(sink.events) == 300
        assert sink.batches == 3  # batch_max 100
        assert not sink.is_open


class TestIsolation:
    """A failing and a hung sink do not change what a healthy sink receives."""

    async def deliver(self, *bad: MemorySink) -> list[str]:
        good = MemorySink("good")
        sinks = {"good": good, **{s.name: s for s in bad}}
        inst = Instruments()
        spool = Spool()
        runners = {
            name: SinkRunner(entry(name), sink, inst, spool=spool) for name, sink in sinks.items()
        }
        bus = Bus([RouteConfig(sinks=tuple(sinks))], runners, inst, spool=spool)
        with anyio.fail_after(10):
            async with anyio.create_task_group() as tg:
                for runner in runners.values():
                    await tg.start(runner.run)
                start = time.perf_counter()
                for n in range(2000):
                    bus.publish(detection(n))
                    if n % 100 == 0:
                        await anyio.lowlevel.checkpoint()
                publish_s = time.perf_counter() - start
                await good.wait_for(2000)
                tg.cancel_scope.cancel()
        for sink in bad:
            runner = runners[sink.name]
            # Nothing was lost for the bad sinks either: it is all still queued for them.
            assert sum(runner.depth) + len(sink.events) == 2000
        assert publish_s < 5  # publish never waited on a sink (a hang would never return)
        return [e.event_id for e in good.events]

    @pytest.mark.anyio
    async def test_failing_and_hung_sinks_do_not_change_what_others_get(self) -> None:
        baseline = await self.deliver()
        failing = MemorySink("failing")
        failing.fail_transient = True
        hung = MemorySink("hung")
        hung.hang = True
        assert await self.deliver(failing, hung) == baseline
        assert baseline == [f"det-{n}" for n in range(2000)]


class TestRoutes:
    """Routes select sinks by kind, airframe and class, and thin latest-wins kinds."""

    def make(self, *routes: RouteConfig) -> tuple[Bus, dict[str, SinkRunner], Instruments]:
        inst = Instruments()
        spool = Spool()
        runners = {n: SinkRunner(entry(n), MemorySink(n), inst, spool=spool) for n in ("a", "b")}
        return Bus(routes, runners, inst, spool=spool), runners, inst

    def test_filters_by_kind_airframe_and_class(self) -> None:
        bus, runners, _ = self.make(
            RouteConfig(sinks=("a",), kinds=(EventKind.TELEMETRY,), airframes=("A",)),
            RouteConfig(sinks=("b",), classes=("tank",)),
        )
        bus.publish(telemetry("A", 1))
        bus.publish(telemetry("B", 1))
        bus.publish(detection(1, "tank"))
        bus.publish(detection(2, "truck"))
        assert runners["a"].depth == (1, 0)
        # b: both telemetry (a class filter does not apply to telemetry) and the tank only.
        assert runners["b"].depth == (2, 1)

    def test_rate_limit_thins_telemetry_but_never_detections(self) -> None:
        bus, runners, inst = self.make(RouteConfig(sinks=("a",), max_rate_hz=0.001))
        for n in range(10):
            bus.publish(telemetry("A", n))
            bus.publish(detection(n))
        assert runners["a"].depth == (1, 10)
        assert inst.sink_rate_limited.labels("a").value == 9
