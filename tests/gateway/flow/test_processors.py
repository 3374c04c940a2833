"""ProcessorRunner: a bounded inbox, restarts after a failure, never fed its own output."""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime

import anyio
import anyio.abc
import pytest
from anyio.streams.memory import MemoryObjectReceiveStream

from gateway.events import BlueForce, Event, EventKind, Position
from gateway.flow.bus import Bus
from gateway.flow.processors import ProcessorRunner
from gateway.ops.instruments import Instruments
from gateway.testing import eventually

T0 = datetime(2026, 11, 23, 12, tzinfo=UTC)


def blue(n: int, uid: str = "U") -> BlueForce:
    return BlueForce(
        event_id=f"b-{uid}-{n}", uid=uid, time=T0, position=Position(lat_deg=1, lon_deg=1),
        source="test",
    )  # fmt: skip


class Echo:
    """Consumes blue force and publishes it again under another uid: its own kind."""

    name = "echo"

    def __init__(self, *, fail_first: bool = False) -> None:
        self.fail_first = fail_first
        self.seen: list[str] = []

    @property
    def kinds(self) -> frozenset[EventKind]:
        return frozenset({EventKind.BLUE_FORCE})

    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Callable[[Event], None],
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        task_status.started()
        async for event in events:
            assert isinstance(event, BlueForce)
            self.seen.append(event.uid)
            if self.fail_first:
                self.fail_first = False
                raise RuntimeError("a bug in the processor")
            publish(blue(len(self.seen), uid=f"echo-of-{event.uid}"))


@pytest.mark.anyio
async def test_a_failing_processor_restarts_and_is_never_fed_its_own_output() -> None:
    inst = Instruments()
    published: list[Event] = []
    processor = Echo(fail_first=True)
    bus: Bus | None = None

    def publish(event: Event) -> None:
        published.append(event)
        assert bus is not None
        bus.publish(event)

    runner = ProcessorRunner("echo", "echo", processor, inst, publish, queue_max=4)
    bus = Bus((), {}, inst, processors=[runner])
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(runner.run)
            bus.publish(blue(1))
            await eventually(lambda: runner.record.restarts == 1)
            bus.publish(blue(2))
            await eventually(lambda: len(published) == 1)
            tg.cancel_scope.cancel()
    assert processor.seen == ["U", "U"]  # its echo never came back to it
    assert [e.uid for e in published] == ["echo-of-U"]  # type: ignore[union-attr]
    assert runner.status()["events_out"] == 1


def test_a_full_inbox_drops_and_counts_instead_of_blocking() -> None:
    inst = Instruments()
    runner = ProcessorRunner("slow", "echo", Echo(), inst, lambda e: None, queue_max=2)
    for n in range(5):
        runner.offer_slot(blue(n), 0.0, None)
    runner.close()
    status = runner.status()
    assert (status["events_in"], status["dropped"]) == (2, 3)
