"""The CoT source: real ATAK/WinTAK events become BlueForce; no-fix positions are rejected."""

from __future__ import annotations

from pathlib import Path

import anyio
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.app import Gateway
from gateway.config import Config
from gateway.cot_listener import CotListener, CotSourceConfig
from gateway.events import BlueForce, Event
from gateway.testing import MemorySink, eventually, fuzz_examples

CORPUS = Path(__file__).resolve().parents[2].parent / "shared" / "corpus" / "cot"
METRICS = CORPUS / "freetakserver_example_metrics" / "cot"

FRIEND = (
    b'<?xml version="1.0" encoding="UTF-8"?>\n<event version="2.0" uid="ANDROID-1" '
    b'type="a-f-G-U-C" how="m-g" time="2026-11-22T10:00:00Z" start="2026-11-22T10:00:00Z" '
    b'stale="2026-11-22T10:05:00Z"><point lat="65.82" lon="21.69" hae="9999999.0" '
    b'ce="9999999.0" le="9999999.0"/><detail><contact callsign="3 PLUT"/></detail></event>'
)


def listener(events: list[Event], uri: str = "udp://127.0.0.1:0") -> CotListener:
    return CotListener(CotSourceConfig(uri=uri), events.append)


@pytest.mark.corpus
def test_real_atak_and_wintak_events_all_parse_and_no_fix_is_rejected() -> None:
    if not METRICS.exists():
        pytest.skip("shared corpus absent")
    events: list[Event] = []
    source = listener(events)
    files = sorted(METRICS.rglob("*.xml"))
    for path in files:
        source.handle(path.read_bytes())
    assert len(files) == 887
    assert "invalid" not in source.counts  # every real client event passes our validator
    assert source.counts["no_fix"] == 474  # the ATAK tablet without GPS, near 0,0
    assert source.counts["accepted"] == len(events)
    friendly = [e for e in events if isinstance(e, BlueForce)]
    assert friendly
    assert all(abs(e.position.lat_deg) > 1 for e in friendly)
    assert sum(source.counts.values()) == 887


def test_friendly_position_becomes_blue_force() -> None:
    events: list[Event] = []
    listener(events).handle(FRIEND)
    (event,) = events
    assert isinstance(event, BlueForce)
    assert (event.uid, event.callsign, event.position.lat_deg) == ("ANDROID-1", "3 PLUT", 65.82)
    assert event.position.alt_hae_m is None


def test_hostile_and_invalid_events_are_counted_not_published() -> None:
    events: list[Event] = []
    source = listener(events)
    source.handle(FRIEND.replace(b"a-f-G-U-C", b"a-h-G"))
    source.handle(FRIEND.replace(b'lat="65.82"', b'lat="91"'))
    source.handle(b"not xml")
    assert events == []
    assert source.counts == {"not_friendly": 1, "invalid": 2}


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(st.binary(max_size=3000))
def test_arbitrary_bytes_never_raise(blob: bytes) -> None:
    events: list[Event] = []
    source = listener(events)
    source.handle(blob)
    source.handle(FRIEND[:40] + blob)
    assert sum(source.counts.values()) == 2


@pytest.mark.anyio
async def test_udp_and_tcp_sources_feed_the_gateway() -> None:
    config = Config.model_validate(
        {
            "health": {"enabled": False},
            "sources": [
                {"name": "mesh", "uri": "udp://127.0.0.1:0"},
                {"name": "stream", "uri": "tcp://127.0.0.1:0"},
            ],
            "sinks": [{"name": "mem", "type": "memory"}],
            "routes": [{"sinks": ["mem"], "kinds": ["blue_force"]}],
        }
    )
    mem = MemorySink("mem")
    gateway = Gateway(config, sinks={"mem": mem})
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            udp, tcp = gateway.sources
            async with await anyio.create_connected_udp_socket(
                remote_host="127.0.0.1", remote_port=udp.local_port
            ) as sock:
                await sock.send(FRIEND)
            async with await anyio.connect_tcp("127.0.0.1", tcp.local_port) as stream:
                second = FRIEND.replace(b"ANDROID-1", b"ANDROID-2")
                await stream.send(second + b"\n" + FRIEND.replace(b"ANDROID-1", b"ANDROID-3"))
            await eventually(
                lambda: len({e.uid for e in mem.events if isinstance(e, BlueForce)}) == 3
            )
            gateway.shutdown()
    assert gateway.status()["sources"][1]["counts"] == {"accepted": 2}
