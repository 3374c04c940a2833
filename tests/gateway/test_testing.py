"""The test doubles shipped in gateway.testing."""

from __future__ import annotations

from datetime import UTC, datetime

import anyio
import pytest

from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import Telemetry
from gateway.testing import MemorySink, NullSink, eventually

EVENT = Telemetry(event_id="1", airframe="A", time=datetime(2026, 11, 22, tzinfo=UTC))


def test_null_sink_counts_and_keeps_nothing() -> None:
    sink = NullSink("n")
    anyio.run(sink.send, [EVENT, EVENT])
    assert sink.count == 2
    assert not hasattr(sink, "events")


def test_null_sink_sends_now_and_counts() -> None:
    sink = NullSink("n")
    assert sink.send_now([EVENT, EVENT]) == 2
    assert sink.count == 2


def test_memory_sink_fails_as_told() -> None:
    sink = MemorySink("m")
    sink.fail_transient = True
    with pytest.raises(TransientSinkError):
        anyio.run(sink.send, [EVENT])
    sink.fail_transient, sink.fail_permanent = False, True
    with pytest.raises(PermanentSinkError):
        anyio.run(sink.send, [EVENT])
    assert sink.events == []


@pytest.mark.anyio
async def test_memory_sink_wait_for_and_eventually() -> None:
    sink = MemorySink("m")
    with anyio.fail_after(5):
        async with anyio.create_task_group() as tg:
            tg.start_soon(sink.send, [EVENT])
            assert await sink.wait_for(1) == [EVENT]
            await eventually(lambda: sink.batches == 1)
