"""The Sink contract, run over every sink the project registers under the entry-point group."""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import anyio
import pytest
from gute_peer import GutePeer
from nats_server import NatsServer
from own_plugins import own_types
from pydantic import ValidationError
from slb_peer import SlbPeer
from sweccis_peer import SweccisPeer

from gateway.c2.plugins import GROUP, build_sink, load_plugin
from gateway.c2.sink import Sink, SinkConfig
from gateway.contract import sample_events
from gateway.errors import SinkLoadError
from gateway.events import EventKind

ROOT = Path(__file__).resolve().parents[2]
SINK_TYPES = own_types(GROUP)  # a third-party sink installed beside us is not ours to test

#: Options that let each built-in sink run inside a test's temporary directory.
OPTIONS: dict[str, Any] = {
    "jsonl": lambda tmp: {"path": str(tmp / "contract.jsonl")},
    # The discard port on loopback: nothing listens, and UDP does not care.
    "cot": lambda tmp: {"destinations": [{"uri": "udp://127.0.0.1:9"}]},
    "nffi": lambda tmp: {"path": str(tmp / "contract.nffi.xml")},
    "ra180": lambda tmp: {"udp": {"host": "127.0.0.1", "port": 9}},
    "klv": lambda tmp: {"udp": {"host": "127.0.0.1", "port": 9}},
    "map": lambda tmp: {"port": 0},  # a free port on loopback
}


@contextmanager
def options_for(type_name: str, tmp_path: Path) -> Iterator[dict[str, Any]]:
    """The options of one built-in sink, with any peer it needs running for the block."""
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


def test_builtin_sinks_are_registered_as_entry_points() -> None:
    assert {"console", "jsonl", "memory"} <= set(SINK_TYPES)


@pytest.mark.parametrize("type_name", SINK_TYPES)
def test_sink_declares_a_frozen_strict_config_model(type_name: str) -> None:
    plugin = load_plugin(type_name)
    assert issubclass(plugin.factory.config_model, SinkConfig)
    with pytest.raises(ValidationError, match="Extra inputs"):
        plugin.factory.config_model.model_validate({"no_such_option_anywhere": 1})


@pytest.mark.parametrize("type_name", SINK_TYPES)
def test_sink_opens_takes_a_batch_and_closes(type_name: str, tmp_path: Path) -> None:
    with options_for(type_name, tmp_path) as options:
        sink = build_sink(type_name, f"contract-{type_name}", options)
        assert isinstance(sink, Sink)
        assert sink.kinds <= frozenset(EventKind)
        # Telemetry where the sink takes it (most do); a handoff-only sink gets a handoff.
        kind = EventKind.TELEMETRY if EventKind.TELEMETRY in sink.kinds else min(sink.kinds)
        event = sample_events(frozenset({kind}))[0]

        async def exercise() -> None:
            with anyio.fail_after(5):
                await sink.open()
                await sink.send([event])
                await sink.aclose()

        anyio.run(exercise)


@pytest.mark.parametrize("type_name", SINK_TYPES)
def test_every_sink_has_a_test_module_and_a_readme_entry(type_name: str) -> None:
    plugin = load_plugin(type_name)
    if plugin.distribution != "fischer-gateway":
        pytest.skip("third-party sink")
    readme = (ROOT / "README.md").read_text()
    assert re.search(rf"\*\*`{type_name}`\*\*", readme), f"README has no entry for {type_name}"
    if type_name not in ("memory", "null"):  # test doubles: tests/gateway/test_testing.py
        here = ROOT / "tests" / "sinks"  # the integration's own folder, or the generic sinks'
        name = f"test_{type_name}.py"
        assert (here / type_name / name).exists() or (here / name).exists(), name


def test_unknown_sink_type_names_the_installed_ones() -> None:
    with pytest.raises(SinkLoadError, match=r"unknown sink type 'nope'.*jsonl"):
        load_plugin("nope")


def test_group_name_is_the_documented_one() -> None:
    assert GROUP == "fischer_gateway.sinks"
    assert 'entry-points."fischer_gateway.sinks"' in (ROOT / "pyproject.toml").read_text()
