"""The spool under the sink runner: stale rules, the circuit breaker, acknowledgements."""

from __future__ import annotations

import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

import anyio
import pytest

from gateway.c2.circuit import Circuit, CircuitState
from gateway.c2.outbox import Outbox
from gateway.c2.sinkrunner import SinkRunner
from gateway.config import RouteConfig, SinkEntry, StaleRule
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import Detection, Event, EventKind, Position, Sensor
from gateway.fleet.acks import DetectionAcks
from gateway.flow.bus import Bus
from gateway.ops.instruments import Instruments
from gateway.spool.store import Spool
from gateway.testing import MemorySink, eventually

T0 = datetime(2026, 11, 23, 12, 0, tzinfo=UTC)


def detection(n: int) -> Detection:
    return Detection(
        event_id=f"det-{n}",
        airframe="F26E-001",
        time=T0,
        sensor=Sensor.IR,
        object_class="tank",
        confidence=0.8,
        position=Position(lat_deg=65.8, lon_deg=21.7),
        sigma_h_m=10.0,
    )


def age(spool: Spool, seconds: float) -> None:
    """Make every spooled event look ``seconds`` older (an outage that long)."""
    assert spool.flush()  # with a loop running, appends wait for the end of the pass
    spool._db.execute("UPDATE events SET spooled_at = spooled_at - ?", (seconds,))


class TestStaleRules:
    def test_deliver_late_marks_the_event_with_how_long_it_waited(self) -> None:
        spool = Spool()
        spool.append(detection(1), ("s",))
        age(spool, 900)
        stale = {EventKind.DETECTION: StaleRule(after_s=600, action="deliver_late")}
        outbox = Outbox("s", spool, window=10, stale=stale)
        taken, expired = outbox.take(10)
        assert expired == []
        (item,) = taken
        late = getattr(item.event, "late_by_s", None)
        assert late is not None
        assert 899 < late < 910

    def test_expire_dead_letters_with_the_reason_and_sends_the_fresh(self) -> None:
        spool = Spool()
        spool.append(detection(1), ("s",))
        age(spool, 120)
        spool.append(detection(2), ("s",))
        stale = {EventKind.DETECTION: StaleRule(after_s=60, action="expire")}
        outbox = Outbox("s", spool, window=10, stale=stale)
        taken, expired = outbox.take(10)
        assert [i.event.event_id for i in taken] == ["det-2"]
        ((item, reason),) = expired
        assert item.event.event_id == "det-1"
        assert reason == "expired: stale after 60 s in the spool"

    @pytest.mark.anyio
    async def test_through_the_runner_expired_events_are_dead_letters_on_disk(
        self, tmp_path: Path
    ) -> None:
        spool = Spool(tmp_path / "spool.db")
        for n in range(3):
            spool.append(detection(n), ("m",))
        age(spool, 7200)
        inst = Instruments()
        sink = MemorySink("m")
        stale = {EventKind.DETECTION: StaleRule(after_s=3600, action="expire")}
        runner = SinkRunner(
            SinkEntry(name="m", type="memory"), sink, inst, spool=spool, stale=stale
        )
        runner.offer(detection(9), time.monotonic())
        with anyio.fail_after(10):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await sink.wait_for(1)
                await eventually(lambda: runner.depth == (0, 0))
                tg.cancel_scope.cancel()
        assert [e.event_id for e in sink.events] == ["det-9"]
        assert inst.sink_dropped.labels("m", "expired").value == 3
        assert sorted(d.event_id for d in spool.dead_letters()) == ["det-0", "det-1", "det-2"]
        spool.close()


class TestCircuit:
    def test_opens_after_three_failures_then_probes_then_closes(self) -> None:
        circuit = Circuit(initial_s=1.0, max_s=30.0)
        for expected_ceiling in (1.0, 2.0):
            delay = circuit.failed()
            assert 0.0 <= delay <= expected_ceiling
            assert circuit.state is CircuitState.CLOSED
            assert not circuit.probing()
        assert 0.0 <= circuit.failed() <= 4.0
        assert circuit.state is CircuitState.OPEN
        assert circuit.probing()
        assert circuit.state is CircuitState.HALF_OPEN
        circuit.failed()
        assert circuit.state is CircuitState.OPEN
        assert circuit.succeeded() == 4
        assert circuit.state is CircuitState.CLOSED
        assert not circuit.probing()

    def test_the_delay_never_exceeds_the_cap_however_long_the_outage(self) -> None:
        circuit = Circuit(initial_s=0.5, max_s=30.0)
        delays = [circuit.failed() for _ in range(10_000)]
        assert max(delays) <= 30.0
        assert max(delays[-100:]) > 15.0  # full jitter up to the cap, not stuck low

    @pytest.mark.anyio
    async def test_an_open_circuit_sends_one_event_as_a_probe(self) -> None:
        class Counting(MemorySink):
            def __init__(self) -> None:
                super().__init__("p")
                self.sizes: list[int] = []

            async def send(self, batch: Sequence[Event]) -> None:
                self.sizes.append(len(batch))
                if len(self.sizes) <= 4:
                    raise TransientSinkError("C2 down", sink=self.name)
                await super().send(batch)

        sink = Counting()
        entry = SinkEntry(name="p", type="memory", retry_initial_s=0.01, retry_max_s=0.02)
        inst = Instruments()
        runner = SinkRunner(entry, sink, inst)
        for n in range(20):
            runner.offer(detection(n), time.monotonic())
        with anyio.fail_after(10):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await sink.wait_for(20)
                tg.cancel_scope.cancel()
        # Three full batches fail and open the circuit; the probe after it is one event,
        # it fails too, the next probe succeeds and full batches resume.
        assert sink.sizes[:3] == [20, 20, 20]
        assert sink.sizes[3:5] == [1, 1]
        assert sink.sizes[5] == 19
        assert [e.event_id for e in sink.events] == [f"det-{n}" for n in range(20)]
        assert inst.sink_circuit.labels("p").value == 0.0


class FakeAirframe:
    """What the acknowledgement path uses of an airframe session."""

    id = "F26E-001"

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def encode_detection_ack(self, detection_id: int, time_usec: int, result: int) -> bytes:
        return f"{detection_id}/{time_usec}/{result};".encode()

    async def send(self, frames: bytes) -> None:
        self.sent.append(frames)


class TestAcknowledgements:
    def acks(self, spool: Spool, held: bool) -> tuple[DetectionAcks, list[Event], Instruments]:
        published: list[Event] = []

        def publish(event: Event) -> bool:
            published.append(event)
            return held and spool.append(event, ("slb",)) is not None

        inst = Instruments()
        return DetectionAcks(publish, spool, inst), published, inst

    def test_held_then_duplicate_and_nothing_for_what_the_spool_refused(self) -> None:
        spool = Spool()
        acks, published, inst = self.acks(spool, held=True)
        airframe = FakeAirframe()
        acks.take(airframe, "radio", detection(1), 1, 100)  # type: ignore[arg-type]
        acks.take(airframe, "radio", detection(1), 1, 100)  # type: ignore[arg-type]
        acks.commit()
        assert [e.event_id for e in published] == ["det-1"]  # the re-send is not published
        assert [frame for _, frame in acks._queue] == [b"1/100/0;", b"1/100/1;"]
        assert inst.detections_acked.labels("F26E-001", "held").value == 1
        assert inst.detections_acked.labels("F26E-001", "duplicate").value == 1

        full, published, _ = self.acks(Spool(), held=False)
        full.take(airframe, "radio", detection(2), 2, 200)  # type: ignore[arg-type]
        full.commit()
        assert len(published) == 1
        assert not full._queue

    def test_a_failed_commit_acknowledges_nothing(self) -> None:
        spool = Spool()
        acks, _, _ = self.acks(spool, held=True)
        acks.take(FakeAirframe(), "radio", detection(1), 1, 100)  # type: ignore[arg-type]
        spool._db.close()  # the disk went away under the open transaction
        with pytest.raises(Exception):  # noqa: B017, PT011 - sqlite's own error, any
            spool._db.execute("SELECT 1")
        acks.commit()
        assert not acks._queue


class TestRefusals:
    @pytest.mark.anyio
    async def test_each_refused_event_keeps_its_own_reason(self) -> None:
        class Picky(MemorySink):
            async def send(self, batch: Sequence[Event]) -> None:
                odd = {
                    e.event_id: f"422 {e.event_id} unknown" for e in batch if e.event_id[-1] in "13"
                }
                self.events.extend(e for e in batch if e.event_id not in odd)
                if odd:
                    raise PermanentSinkError("2 refused", sink=self.name, reasons=odd)

        sink = Picky("p")
        spool = Spool()
        runner = SinkRunner(SinkEntry(name="p", type="memory"), sink, Instruments(), spool=spool)
        for n in range(4):
            runner.offer(detection(n), time.monotonic())
        with anyio.fail_after(10):
            async with anyio.create_task_group() as tg:
                await tg.start(runner.run)
                await eventually(lambda: runner.depth == (0, 0))
                tg.cancel_scope.cancel()
        assert [e.event_id for e in sink.events] == ["det-0", "det-2"]
        letters = {d.event_id: d.reason for d in spool.dead_letters()}
        assert letters == {"det-1": "422 det-1 unknown", "det-3": "422 det-3 unknown"}
        assert runner.status()["dead_letters"] == 2


def test_a_detection_the_full_spool_refused_reaches_no_processor_either() -> None:
    class Fusion:
        name = "fusion"
        kinds = frozenset({EventKind.DETECTION})
        description = "processor 'fusion'"

        def __init__(self) -> None:
            self.got: list[str] = []

        def offer_slot(self, event: Event, ingest_mono: float, slot: str | None) -> None:
            self.got.append(event.event_id)

    spool = Spool(max_bytes=64 * 1024)
    inst = Instruments()
    runner = SinkRunner(SinkEntry(name="slb", type="memory"), MemorySink("slb"), inst, spool=spool)
    fusion = Fusion()
    bus = Bus(
        [RouteConfig(sinks=("slb",))], {"slb": runner}, inst, processors=[fusion], spool=spool
    )
    held = [bus.publish(detection(n)) for n in range(2000)]
    assert not all(held)
    assert fusion.got == [f"det-{n}" for n, ok in enumerate(held) if ok]


@pytest.mark.anyio
async def test_events_of_a_batch_that_never_committed_are_not_delivered() -> None:
    spool = Spool()
    sink = MemorySink("slb")
    inst = Instruments()
    runner = SinkRunner(SinkEntry(name="slb", type="memory"), sink, inst, spool=spool)
    bus = Bus([RouteConfig(sinks=("slb",))], {"slb": runner}, inst, spool=spool)

    def failing_datagram() -> None:
        with spool.batch():
            assert bus.publish(detection(1))
            raise OSError("disk gone")

    with pytest.raises(OSError, match="disk gone"):
        failing_datagram()
    assert bus.publish(detection(2))
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(runner.run)
            await sink.wait_for(1)
            await eventually(lambda: runner.depth == (0, 0))
            tg.cancel_scope.cancel()
    assert [e.event_id for e in sink.events] == ["det-2"]


def test_remembered_detection_ids_never_lock_out_durable_events() -> None:
    spool = Spool(max_bytes=2 * 1024 * 1024, seen_max=10**9)
    n = 0
    while not spool.is_full:  # a flood of fresh ids from an unsecured link
        with spool.batch():
            for _ in range(500):
                spool.remember(f"flood-{n}")
                n += 1
        spool._bytes = spool._measure()
    held = [spool.append(detection(k), ("slb",)) for k in range(2000)]
    assert any(seq is not None for seq in held[-300:])  # the oldest ids made room
    assert spool.pending_count("slb") > 0


def test_the_remembered_ids_are_capped() -> None:
    spool = Spool(seen_max=25_000)
    for k in range(60_000):
        spool.remember(f"id-{k}")
    rows = spool._db.execute("SELECT count(*) FROM seen").fetchone()[0]
    assert rows <= 25_000 + 1
    assert spool.seen("id-59999")
    assert not spool.seen("id-0")
