"""The CoT source: real ATAK/WinTAK events become BlueForce; no-fix positions are rejected."""

from __future__ import annotations

import socket
from pathlib import Path

import anyio
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

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
    assert source.parsed == 887  # every real ATAK/WinTAK event passes our validator
    assert source.counts["no_fix"] == 474  # the ATAK tablet without GPS, near 0,0
    assert source.counts["accepted"] == len(events) == 265  # 228 WinTAK, 37 ATAK with a fix
    assert all(isinstance(e, BlueForce) and e.source == "cot" for e in events)
    assert all(abs(e.position.lat_deg) > 1 for e in events)  # type: ignore[union-attr]
    assert sum(source.counts.values()) == 887


@pytest.mark.corpus
def test_the_other_real_events_parse_too() -> None:
    """ATAK-CIV's reference events and a peer gateway's event pass; no blue force is invented."""
    files = sorted((CORPUS / "atak_civ_takcot" / "examples").glob("*.cot"))
    files.append(CORPUS / "cotproxy" / "sample.xml")
    if not files[0].exists():
        pytest.skip("shared corpus absent")
    events: list[Event] = []
    source = listener(events)
    for path in files:
        source.handle(path.read_bytes())
    assert source.parsed == len(files) == 13
    assert events == []  # shapes, markers and an AIS aid to navigation: none friendly


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
    assert source.problems == {"position": 1, "xml": 1}


def test_protobuf_mesh_positions_are_taken_too() -> None:
    """ATAK switches the mesh to TAK protocol v1 when its peers speak it."""
    takproto = pytest.importorskip("takproto")
    events: list[Event] = []
    source = listener(events)
    source.handle(bytes(takproto.xml2proto(FRIEND, takproto.TAKProtoVer.MESH)))
    no_fix = FRIEND.replace(b'lat="65.82" lon="21.69"', b'lat="0.001" lon="-0.002"')
    source.handle(bytes(takproto.xml2proto(no_fix, takproto.TAKProtoVer.MESH)))
    (event,) = events
    assert isinstance(event, BlueForce)
    assert (event.uid, event.callsign, event.position.lat_deg) == ("ANDROID-1", "3 PLUT", 65.82)
    assert source.counts == {"accepted": 1, "no_fix": 1}


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(st.binary(max_size=3000))
def test_arbitrary_bytes_never_raise(blob: bytes) -> None:
    events: list[Event] = []
    source = listener(events)
    source.handle(blob)
    source.handle(FRIEND[:40] + blob)
    source.handle(b"\xbf\x01\xbf" + blob)
    assert sum(source.counts.values()) == 3


@pytest.mark.anyio
async def test_multicast_group_on_loopback() -> None:
    events: list[Event] = []
    source = CotListener(
        CotSourceConfig(uri="udp+multicast://239.2.3.1:0", interface="127.0.0.1"), events.append
    )
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            try:
                await tg.start(source.run)
            except OSError as exc:
                pytest.skip(f"this host cannot join a multicast group on loopback: {exc}")
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
                sender.setsockopt(
                    socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1")
                )
                sender.sendto(FRIEND, ("239.2.3.1", source.local_port))
                await eventually(lambda: bool(events))
            tg.cancel_scope.cancel()
    assert [e.uid for e in events] == ["ANDROID-1"]  # type: ignore[union-attr]


@pytest.mark.anyio
async def test_tcp_stream_without_an_end_is_cut_off() -> None:
    events: list[Event] = []
    config = CotSourceConfig(uri="tcp://127.0.0.1:0", max_event_bytes=1024, max_clients=1)
    source = CotListener(config, events.append)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            async with await anyio.connect_tcp("127.0.0.1", source.local_port) as stream:
                await stream.send(FRIEND + b"<event " + b"x" * 2000)
                with pytest.raises((anyio.EndOfStream, anyio.BrokenResourceError)):
                    await stream.receive()  # the listener hung up
            tg.cancel_scope.cancel()
    assert source.counts == {"accepted": 1, "oversize": 1}


@pytest.mark.anyio
async def test_tcp_clients_beyond_the_limit_are_refused() -> None:
    events: list[Event] = []
    config = CotSourceConfig(uri="tcp://127.0.0.1:0", max_clients=1)
    source = CotListener(config, events.append)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            async with await anyio.connect_tcp("127.0.0.1", source.local_port) as first:
                await first.send(FRIEND)
                await eventually(lambda: bool(events))
                async with await anyio.connect_tcp("127.0.0.1", source.local_port) as second:
                    with pytest.raises((anyio.EndOfStream, anyio.BrokenResourceError)):
                        await second.receive()
            tg.cancel_scope.cancel()
    assert source.refused_clients == 1


@pytest.mark.parametrize(
    ("uri", "message"),
    [("http://h:1", "expected udp://"), ("udp+multicast://10.1.1.1:6969", "not a multicast")],
)
def test_source_uris_are_checked(uri: str, message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        CotSourceConfig(uri=uri)


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
    assert all(e.source == "cot" for e in mem.events if isinstance(e, BlueForce))
