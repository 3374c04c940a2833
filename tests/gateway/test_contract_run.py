"""gateway.contract.check_source and check_processor: pass what we ship, name each broken rule."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, ClassVar

import anyio
import anyio.abc
import pytest
from anyio.streams.memory import MemoryObjectReceiveStream
from nats_server import NatsServer
from own_plugins import own_types
from pydantic import ConfigDict, Field
from slb_peer import SlbPeer
from sweccis_peer import SweccisPeer

from gateway.c2.plugins import PROCESSOR_GROUP, SOURCE_GROUP, load_component
from gateway.contract import (
    ContractViolation,
    ProcessorConfig,
    Publish,
    SourceConfig,
    check_processor,
    check_source,
)
from gateway.events import BlueForce, Event, EventKind, Position, Telemetry
from gateway.testing import eventually
from sinks.cot.source import CotSource

#: While FRIEND is current (between its start and its stale).
NOW = datetime(2026, 11, 22, 10, 1, tzinfo=UTC)
FRIEND = (
    b'<?xml version="1.0" encoding="UTF-8"?>\n<event version="2.0" uid="ANDROID-1" '
    b'type="a-f-G-U-C" how="m-g" time="2026-11-22T10:00:00Z" start="2026-11-22T10:00:00Z" '
    b'stale="2026-11-22T10:05:00Z"><point lat="65.82" lon="21.69" hae="9999999.0" '
    b'ce="9999999.0" le="9999999.0"/><detail><contact callsign="3 PLUT"/></detail></event>'
)
PROCESSOR_OPTIONS: dict[str, dict[str, Any]] = {
    "counter_uas": {
        "batteries": [
            {"id": "GUTE-1", "lat_deg": 65.80, "lon_deg": 21.70, "effectors": ["TRACKFIRE_30MM"]}
        ]
    },
}


@contextmanager
def source_options(type_name: str, tmp_path: Path) -> Iterator[dict[str, Any]]:
    """The options of one source we ship, with any peer it needs running for the block."""
    if type_name == "slb":  # a real HTTPS SLB on loopback, in a thread
        with SlbPeer(tmp_path).in_thread() as slb:
            yield slb.source_options()
    elif type_name == "sweccis":  # a real SWECCIS server (TLS, frames, XSD) on loopback
        with SweccisPeer(tmp_path).in_thread() as sweccis:
            yield sweccis.link_options()
    elif type_name == "local":
        yield {"socket": str(tmp_path / "orders.sock")}
    elif type_name == "nffi":
        yield {"uri": "tcp://127.0.0.1:0", "allow": ["127.0.0.1/32"]}
    elif type_name == "cot":
        yield {"uri": "udp://127.0.0.1:0"}
    elif type_name == "nats":  # a real nats-server (JetStream) on loopback
        with NatsServer(tmp_path, "contract") as server:
            yield {"node": "contract", "servers": [server.url], "remotes": ["brigade"]}
    else:
        pytest.fail(f"a new source {type_name!r}: give it options here")


@pytest.mark.parametrize("type_name", own_types(SOURCE_GROUP))
def test_every_source_we_ship_passes(type_name: str, tmp_path: Path) -> None:
    with source_options(type_name, tmp_path) as options:
        check_source(load_component(SOURCE_GROUP, type_name).factory, options)


@pytest.mark.parametrize("type_name", own_types(PROCESSOR_GROUP))
def test_every_processor_we_ship_passes(type_name: str) -> None:
    options = PROCESSOR_OPTIONS.get(type_name, {})
    check_processor(load_component(PROCESSOR_GROUP, type_name).factory, options)


def test_drive_gives_the_running_source_its_input() -> None:
    async def send_friend(source: CotSource) -> None:
        async with await anyio.create_udp_socket(local_host="127.0.0.1") as udp:
            await udp.sendto(FRIEND, "127.0.0.1", source.local_port)
        with anyio.fail_after(5):  # the deadline of drive: generous, it is not timed
            await eventually(lambda: bool(source.status()["counts"]))

    run = check_source(
        CotSource, {"uri": "udp://127.0.0.1:0"}, drive=send_friend, clock=lambda: NOW
    )
    (friend,) = run.published
    assert isinstance(friend, BlueForce)
    assert (friend.uid, friend.callsign) == ("ANDROID-1", "3 PLUT")


def test_the_processor_is_fed_a_sample_of_every_kind_it_consumes() -> None:
    seen: list[Event] = []

    class Echo(Quiet):
        kinds_ = frozenset(EventKind)

        async def run(
            self,
            events: MemoryObjectReceiveStream[Event],
            publish: Publish,
            *,
            task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
        ) -> None:
            task_status.started()
            async for event in events:
                seen.append(event)

    check_processor(Echo)
    assert [e.kind for e in seen] == list(EventKind)


# -- plugins that break one rule each ------------------------------------------------------


class TickerConfig(SourceConfig):
    interval_s: float = Field(default=0.01, gt=0)


class Ticker:
    """Publishes a BlueForce every ``interval_s``: keeps the contract; its subclasses do not."""

    config_model: ClassVar[type[SourceConfig]] = TickerConfig

    def __init__(self, name: str, config: TickerConfig, publish: Publish, *, clock: Any) -> None:
        self.name = name
        self.config = config
        self.publish = publish
        self.clock = clock

    def report(self) -> Event:
        where = Position(lat_deg=65.8, lon_deg=21.7)
        return BlueForce(event_id="t", uid="U", time=self.clock(), position=where, source="t")

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        task_status.started()
        while True:
            self.publish(self.report())
            await anyio.sleep(self.config.interval_s)

    def status(self) -> dict[str, object]:
        return {"source": self.name}


class QuietConfig(ProcessorConfig):
    pass


class Quiet:
    """Reads its events and publishes nothing: keeps the contract; its subclasses do not."""

    config_model: ClassVar[type[ProcessorConfig]] = QuietConfig
    kinds_: frozenset[EventKind] = frozenset({EventKind.DETECTION})

    def __init__(self, name: str, config: QuietConfig) -> None:
        self.name = name

    @property
    def kinds(self) -> frozenset[EventKind]:
        return self.kinds_

    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Publish,
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        task_status.started()
        async for _ in events:
            pass


class LooseTickerConfig(SourceConfig):
    model_config = ConfigDict(frozen=True, extra="ignore")


class LooseTicker(Ticker):
    config_model = LooseTickerConfig


class NamelessTicker(Ticker):
    def __init__(self, name: str, config: TickerConfig, publish: Publish, *, clock: Any) -> None:
        super().__init__("fixed", config, publish, clock=clock)


class SilentTicker(Ticker):
    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        await anyio.sleep_forever()


class CrashingTicker(Ticker):
    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        task_status.started()
        await anyio.sleep(0.01)
        raise RuntimeError("a bug")


class DeafTicker(Ticker):
    """Swallows cancellation and carries on: never ends."""

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        task_status.started()
        cancelled = anyio.Event()
        while not cancelled.is_set():
            try:
                await anyio.sleep(0.05)
            except anyio.get_cancelled_exc_class():
                with anyio.CancelScope(shield=True):
                    await anyio.sleep(2.0)  # long past the check; then it gives up
                cancelled.set()


class BlockingTicker(Ticker):
    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        task_status.started()
        await anyio.sleep(0.01)
        time.sleep(0.3)  # noqa: ASYNC251 - the violation under test
        await anyio.sleep_forever()


class ForgingTicker(Ticker):
    def report(self) -> Event:
        # model_construct skips validation: a latitude no event may carry.
        bad = Position.model_construct(lat_deg=123.0, lon_deg=21.7, alt_msl_m=None)
        return BlueForce.model_construct(**{**super().report().__dict__, "position": bad})


class ThreadedTicker(Ticker):
    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        task_status.started()
        await anyio.to_thread.run_sync(self.publish, self.report())
        await anyio.sleep_forever()


class EagerTicker(Ticker):
    def __init__(self, name: str, config: TickerConfig, publish: Publish, *, clock: Any) -> None:
        super().__init__(name, config, publish, clock=clock)
        publish(self.report())


class MuteTicker(Ticker):
    def status(self) -> dict[str, object]:
        return "fine"  # type: ignore[return-value]


@pytest.mark.parametrize(
    ("factory", "expected"),
    [
        (LooseTicker, "unknown options must be rejected"),
        (NamelessTicker, r"source\.name is 'fixed'"),
        (SilentTicker, r"run\(\) calling task_status\.started\(\) did not happen within 0\.2 s"),
        (CrashingTicker, r"run\(\) raised RuntimeError: a bug before it was cancelled"),
        (DeafTicker, r"run\(\) ending after it was cancelled did not happen within 0\.2 s"),
        (BlockingTicker, r"run\(\) blocked the event loop for \d+\.\d+ s"),
        (ForgingTicker, "published an invalid BlueForce"),
        (ThreadedTicker, "publish.. was called from outside the event loop's thread"),
        (EagerTicker, r"published 1 event\(s\) before run\(\) was started"),
        (MuteTicker, r"status\(\) before run\(\) must return a dict"),
    ],
    ids=lambda v: v.__name__ if isinstance(v, type) else "",
)
def test_a_source_breaking_a_rule_is_named(factory: type[Ticker], expected: str) -> None:
    with pytest.raises(ContractViolation, match=expected):
        check_source(factory, deadline_s=0.2)


def test_a_source_keeping_the_rules_passes_and_its_events_are_returned() -> None:
    run = check_source(Ticker, {"interval_s": 0.01}, clock=lambda: NOW)
    assert run.component.name == "contract"
    assert run.published
    assert all(isinstance(e, BlueForce) for e in run.published)


class KindlessQuiet(Quiet):
    kinds_ = frozenset()


class CrashingQuiet(Quiet):
    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Publish,
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        task_status.started()
        async for event in events:
            raise ValueError(f"cannot take {event.kind}")


class LazyQuiet(Quiet):
    """Reports started but never reads its stream."""

    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Publish,
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        task_status.started()
        await anyio.sleep_forever()


class ForgingQuiet(Quiet):
    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Publish,
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        task_status.started()
        async for event in events:
            publish(Telemetry.model_construct(event_id=event.event_id))  # type: ignore[call-arg]


@pytest.mark.parametrize(
    ("factory", "expected"),
    [
        (KindlessQuiet, "kinds must be a non-empty frozenset of EventKind"),
        (
            CrashingQuiet,
            r"run\(\) raised ValueError: cannot take detection before it was cancelled",
        ),
        (LazyQuiet, r"reading the 1 events fed to run\(\) did not happen within 0\.2 s"),
        (ForgingQuiet, "published an invalid Telemetry"),
    ],
    ids=lambda v: v.__name__ if isinstance(v, type) else "",
)
def test_a_processor_breaking_a_rule_is_named(factory: type[Quiet], expected: str) -> None:
    with pytest.raises(ContractViolation, match=expected):
        check_processor(factory, deadline_s=0.2)


def test_no_check_leaves_a_thread_behind_once_its_plugin_ends() -> None:
    before = set(threading.enumerate())
    check_processor(Quiet)
    assert set(threading.enumerate()) - before == set()
