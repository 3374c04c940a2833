"""gateway.contract.check_sink: passes every sink we ship, catches each broken rule.

(Not test_contract.py: tests/sinks/test_contract.py has that basename.)
"""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from gute_peer import GutePeer
from nats_server import NatsServer
from own_plugins import own_types
from pydantic import ConfigDict
from slb_peer import SlbPeer
from sweccis_peer import SweccisPeer

from gateway.c2.plugins import GROUP, load_plugin
from gateway.c2.sink import SinkConfig
from gateway.contract import ContractViolation, LoopBlocked, check_sink, sample_events
from gateway.events import Event, EventKind, event_adapter
from gateway.testing import MemorySink, MemorySinkConfig
from sinks.example import ExampleSink

OPTIONS: dict[str, Any] = {
    "jsonl": lambda tmp: {"path": str(tmp / "contract.jsonl")},
    "cot": lambda tmp: {"destinations": [{"uri": "udp://127.0.0.1:9"}]},
    "nffi": lambda tmp: {"path": str(tmp / "contract.nffi.xml")},
    "klv": lambda tmp: {"udp": {"host": "127.0.0.1", "port": 9}},
    "ra180": lambda tmp: {"udp": {"host": "127.0.0.1", "port": 9}},
    "map": lambda tmp: {"port": 0},  # a free port on loopback, not the default 8780
}


@contextmanager
def options_for(type_name: str, tmp_path: Path) -> Iterator[dict[str, Any]]:
    """The options of one installed sink, with any peer it needs running for the block."""
    if type_name == "gute2":  # a real HTTPS battery on loopback, in a thread
        with GutePeer(tmp_path).in_thread() as peer:
            yield peer.sink_options()
        return
    if type_name == "slb":  # a real HTTPS SLB on loopback, in a thread
        with SlbPeer(tmp_path).in_thread() as slb:
            yield slb.sink_options()
        return
    if type_name == "sweccis":  # a real SWECCIS server (TLS, frames, XSD) on loopback
        with SweccisPeer(tmp_path).in_thread() as sweccis:
            yield sweccis.link_options()
        return
    if type_name == "nats":  # a real nats-server (JetStream) on loopback
        with NatsServer(tmp_path, "contract") as server:
            yield {"node": "contract", "servers": [server.url]}
        return
    make = OPTIONS.get(type_name)
    yield make(tmp_path) if make else {}


@pytest.mark.parametrize("type_name", own_types(GROUP))
def test_every_sink_we_ship_passes(type_name: str, tmp_path: Path) -> None:
    with options_for(type_name, tmp_path) as options:
        check_sink(load_plugin(type_name).factory, options)


def test_sample_events_cover_every_kind_and_validate() -> None:
    events = sample_events(frozenset(EventKind))
    assert [e.kind for e in events] == list(EventKind)
    for event in events:
        assert event_adapter.validate_json(event.model_dump_json()) == event


def test_the_example_sink_passes_and_delivers_json_datagrams() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
        peer.bind(("127.0.0.1", 0))
        peer.settimeout(5)
        check_sink(ExampleSink, {"port": peer.getsockname()[1]})
        got = [peer.recv(65536) for _ in range(2)]
    assert [event_adapter.validate_json(data).kind for data in got] == [
        EventKind.TELEMETRY,
        EventKind.DETECTION,
    ]


class BlockingSink(MemorySink):
    """Sleeps on the event loop in send: what the contract forbids."""

    async def send(self, batch: Sequence[Event]) -> None:
        time.sleep(0.3)  # noqa: ASYNC251 - the violation under test
        await super().send(batch)


class BlocksOnce(MemorySink):
    """Holds the loop in its first instance's open() only (as a loaded machine may)."""

    built = 0

    def __init__(self, name: str, config: MemorySinkConfig | None = None) -> None:
        super().__init__(name, config)
        type(self).built += 1
        self._first = type(self).built == 1

    async def open(self) -> None:
        if self._first:
            time.sleep(0.3)  # noqa: ASYNC251 - the stall under test
        await super().open()


class NamelessSink(MemorySink):
    def __init__(self, name: str, config: MemorySinkConfig | None = None) -> None:
        super().__init__("fixed", config)


class LooseConfig(SinkConfig):
    model_config = ConfigDict(extra="ignore", frozen=True)


class LooseSink(MemorySink):
    config_model = LooseConfig  # type: ignore[assignment]


class TestViolations:
    """Each broken rule is named."""

    def test_blocking_the_loop(self) -> None:
        with pytest.raises(
            LoopBlocked, match=r"send\(\[\]\) blocked the event loop for \d+\.\d+ s"
        ):
            check_sink(BlockingSink)

    def test_a_loop_held_once_by_something_else_is_not_the_sinks(self) -> None:
        """A machine that deschedules the process looks like a blocking call: the checker
        runs a fresh sink once more, and only one that blocks again is in breach."""
        check_sink(BlocksOnce)
        assert BlocksOnce.built == 2

    def test_ignoring_the_given_name(self) -> None:
        with pytest.raises(ContractViolation, match=r"sink\.name is 'fixed'"):
            check_sink(NamelessSink)

    def test_accepting_unknown_options(self) -> None:
        with pytest.raises(ContractViolation, match="unknown options must be rejected"):
            check_sink(LooseSink)

    def test_no_kinds(self) -> None:
        with pytest.raises(ContractViolation, match="non-empty frozenset of EventKind"):
            check_sink(MemorySink, {"kinds": []})

    def test_a_send_that_never_returns(self) -> None:
        with pytest.raises(ContractViolation, match=r"did not return within 0\.2 s"):
            check_sink(MemorySink, {"hang": True}, deadline_s=0.2)


class AsyncSendNow(MemorySink):
    async def send_now(self, batch: Sequence[Event]) -> int:
        return len(batch)


class CountsWrong(MemorySink):
    def send_now(self, batch: Sequence[Event]) -> int:
        return len(batch) + 1


class SendsNowWell(MemorySink):
    def send_now(self, batch: Sequence[Event]) -> int:
        self.events.extend(batch[:1])
        return min(1, len(batch))


class TestSendNow:
    """The optional synchronous send is checked when a sink has one."""

    def test_an_async_send_now_is_refused(self) -> None:
        with pytest.raises(ContractViolation, match="must be a plain"):
            check_sink(AsyncSendNow)

    def test_a_count_beyond_the_batch_is_refused(self) -> None:
        with pytest.raises(ContractViolation, match=r"send_now\(\) of \d+ events returned"):
            check_sink(CountsWrong)

    def test_a_sink_that_sends_part_now_passes(self) -> None:
        check_sink(SendsNowWell)
