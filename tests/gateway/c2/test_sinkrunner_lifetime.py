"""SinkRunner: sink lifetimes in the runner's task group, backoff bounds, sink bugs, refusals."""

from __future__ import annotations

import time
from collections.abc import Sequence

import anyio
import anyio.abc
import pytest
from structlog.testing import capture_logs

from gateway.c2.sink import LifetimeSink, Sink
from gateway.c2.sinkrunner import ERROR_ATTEMPTS, SinkRunner
from gateway.errors import PermanentSinkError
from gateway.events import Event
from gateway.ops.instruments import Instruments
from gateway.testing import MemorySink, eventually
from tests.gateway.c2.test_sinkrunner import detection, entry, telemetry


class BackgroundSink(MemorySink):
    """A sink with background work: ticks while open, as a mesh announcement would."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.ticks = 0
        self.opens = 0
        self.closes = 0
        self.running = False
        self.fail_run_after: int | None = None
        self.log: list[str] = []

    async def open(self) -> None:
        self.opens += 1
        self.log.append("open")
        await super().open()

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        self.log.append("run")
        self.running = True
        task_status.started()
        try:
            while True:
                self.ticks += 1
                if self.fail_run_after is not None and self.ticks >= self.fail_run_after:
                    self.fail_run_after = None
                    raise RuntimeError("background work broke")
                await anyio.sleep(0.001)
        finally:
            self.running = False
            self.log.append("run-ended")

    async def aclose(self) -> None:
        self.closes += 1
        self.log.append(f"aclose(running={self.running})")
        await super().aclose()


class PickySink(MemorySink):
    """Raises a bug (KeyError) for one event id, and can refuse others permanently by id."""

    def __init__(self, name: str, poisoned: str, refuse: frozenset[str] = frozenset()) -> None:
        super().__init__(name)
        self.poisoned = poisoned
        self.refuse = refuse
        self.calls = 0

    async def send(self, batch: Sequence[Event]) -> None:
        self.calls += 1
        ids = {e.event_id for e in batch}
        if self.poisoned in ids:
            raise KeyError("telemetry")  # the partial stale_s dict of issue 10
        if refused := ids & self.refuse:
            await super().send([e for e in batch if e.event_id not in refused])
            raise PermanentSinkError("not for us", sink=self.name, event_ids=refused)
        await super().send(batch)


class TestLifetime:
    """A sink's background work runs in the runner's task group, between open and aclose."""

    def test_lifetime_sink_is_still_a_plain_sink(self) -> None:
        sink = BackgroundSink("b")
        assert isinstance(sink, LifetimeSink)
        assert isinstance(sink, Sink)
        assert not isinstance(MemorySink("m"), LifetimeSink)

    @pytest.mark.anyio
    async def test_run_starts_after_open_and_is_cancelled_before_aclose(self) -> None:
        sink = BackgroundSink("b")
        runner = SinkRunner(entry("b"), sink, Instruments())
        runner.offer(detection(1), time.monotonic())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await sink.wait_for(1)
                await eventually(lambda: sink.ticks >= 3)  # working alongside the sends
                assert sink.running
                runner.stop()
                await runner.wait_done()
        assert sink.log == ["open", "run", "run-ended", "aclose(running=False)"]

    @pytest.mark.anyio
    async def test_a_failed_lifetime_closes_and_reopens_the_sink(self) -> None:
        sink = BackgroundSink("b")
        sink.fail_run_after = 2
        inst = Instruments()
        runner = SinkRunner(entry("b"), sink, inst)
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: sink.opens == 2 and runner.is_open)
                runner.offer(detection(1), time.monotonic())
                await sink.wait_for(1)  # delivery goes on after the reopen
                tg.cancel_scope.cancel()
        assert sink.log[:5] == ["open", "run", "run-ended", "aclose(running=False)", "open"]
        assert inst.sink_failed.labels("b", "error").value == 1

    @pytest.mark.anyio
    async def test_cancelling_the_runner_cancels_the_lifetime_then_closes(self) -> None:
        sink = BackgroundSink("b")
        runner = SinkRunner(entry("b"), sink, Instruments())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: sink.running)
                tg.cancel_scope.cancel()
        assert sink.log[-2:] == ["run-ended", "aclose(running=False)"]
        assert not runner.is_open


class TestBackoff:
    """Backoff stays bounded whatever the failure count, and never delays a shutdown."""

    @pytest.mark.anyio
    async def test_millions_of_failures_in_a_row_back_off_at_the_cap(self) -> None:
        sink = MemorySink("m")
        sink.fail_transient = True
        inst = Instruments()
        runner = SinkRunner(entry("m", retry_max_s=0.01), sink, inst)
        runner.failures_in_row = 3_000_000  # a TAK server down for weeks
        runner.offer(detection(1), time.monotonic())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: inst.sink_failed.labels("m", "transient").value >= 3)
                sink.fail_transient = False
                await sink.wait_for(1)
                tg.cancel_scope.cancel()
        assert runner.failures_in_row == 0
        runner.failures_in_row = 10**7
        assert runner.retry_delay_s() == 0.01

    @pytest.mark.anyio
    async def test_stop_cuts_a_long_backoff_short(self) -> None:
        sink = MemorySink("m")
        sink.fail_transient = True
        inst = Instruments()
        runner = SinkRunner(entry("m", retry_initial_s=60, retry_max_s=60), sink, inst)
        runner.offer(detection(1), time.monotonic())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: runner.state == "retrying")
                sink.fail_transient = False
                runner.stop()
                await runner.wait_done()  # not a minute later
        assert [e.event_id for e in sink.events] == ["det-1"]


class TestSinkBugs:
    """An unexpected exception is bounded: counted, logged rate-limited, the culprit isolated."""

    @pytest.mark.anyio
    async def test_a_poisoned_event_is_given_up_and_the_rest_delivered_in_order(self) -> None:
        sink = PickySink("p", poisoned="det-2")
        inst = Instruments()
        runner = SinkRunner(entry("p"), sink, inst)
        for n in range(5):
            runner.offer(detection(n), time.monotonic())
        runner.offer(telemetry("A", 1), time.monotonic())
        with capture_logs() as logs, anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await sink.wait_for(5)
                runner.offer(detection(9), time.monotonic())
                await sink.wait_for(6)  # the queue moves on behind it
                tg.cancel_scope.cancel()
        assert [e.event_id for e in sink.events] == [
            "A-1", "det-0", "det-1", "det-3", "det-4", "det-9",
        ]  # fmt: skip
        ((event, reason),) = runner.dead_letters
        assert event.event_id == "det-2"
        assert "KeyError" in reason
        assert inst.sink_failed.labels("p", "error").value == ERROR_ATTEMPTS + 1
        assert inst.sink_dropped.labels("p", "rejected").value == 1
        tracebacks = [e for e in logs if e["event"] == "sink_call_failed" and "exc_info" in e]
        assert len(tracebacks) == 1  # rate-limited; every failure is still counted
        assert [e["event_id"] for e in logs if e["event"] == "sink_event_given_up"] == ["det-2"]

    @pytest.mark.anyio
    async def test_a_poisoned_latest_wins_event_is_dropped_and_counted(self) -> None:
        sink = PickySink("p", poisoned="A-1")
        inst = Instruments()
        runner = SinkRunner(entry("p"), sink, inst)
        runner.offer(telemetry("A", 1), time.monotonic())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: inst.sink_dropped.labels("p", "error").value == 1)
                runner.offer(telemetry("A", 2), time.monotonic())
                await sink.wait_for(1)
                tg.cancel_scope.cancel()
        assert [e.event_id for e in sink.events] == ["A-2"]
        assert not runner.dead_letters
        assert sink.calls == ERROR_ATTEMPTS + 1


class TestRefusals:
    """``PermanentSinkError(event_ids=...)`` dead-letters exactly those events."""

    @pytest.mark.anyio
    async def test_only_the_named_events_are_dead_lettered(self) -> None:
        sink = PickySink("p", poisoned="-", refuse=frozenset({"det-1", "det-3"}))
        inst = Instruments()
        runner = SinkRunner(entry("p"), sink, inst)
        for n in range(5):
            runner.offer(detection(n), time.monotonic())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: len(runner.dead_letters) == 2)
                tg.cancel_scope.cancel()
        assert [e.event_id for e in sink.events] == ["det-0", "det-2", "det-4"]
        assert [e.event_id for e, _ in runner.dead_letters] == ["det-1", "det-3"]
        assert sink.calls == 1  # the delivered three are not sent again
        assert inst.sink_sent.labels("p").value == 3
        assert inst.sink_dropped.labels("p", "rejected").value == 2


class TestTransientErrors:
    """A sink's own TransientSinkError still retries without limit (no give-up)."""

    @pytest.mark.anyio
    async def test_transient_failures_never_give_up(self) -> None:
        sink = MemorySink("m")
        sink.fail_transient = True
        inst = Instruments()
        runner = SinkRunner(entry("m"), sink, inst)
        runner.offer(detection(1), time.monotonic())
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                limit = ERROR_ATTEMPTS * 3
                await eventually(lambda: inst.sink_failed.labels("m", "transient").value > limit)
                tg.cancel_scope.cancel()
        assert not runner.dead_letters
        assert runner.depth == (0, 1)
