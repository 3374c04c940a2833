"""The CoT source: real ATAK/WinTAK events become BlueForce; no-fix positions are rejected."""

from __future__ import annotations

import contextlib
import os
import socket
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import anyio
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from gateway.app import Gateway
from gateway.config import Config
from gateway.domain.peertext import Provenance
from gateway.events import BlueForce, Event
from gateway.testing import MemorySink, eventually, fuzz_examples
from sinks.cot.source import NO_FIX_DEG, CotSource, CotSourceConfig
from sinks.cot.stream import EventSplitter
from sinks.cot.validate import parse_cot

CORPUS = Path(__file__).resolve().parents[3].parent / "shared" / "corpus" / "cot"
METRICS = CORPUS / "freetakserver_example_metrics" / "cot"

FRIEND = (
    b'<?xml version="1.0" encoding="UTF-8"?>\n<event version="2.0" uid="ANDROID-1" '
    b'type="a-f-G-U-C" how="m-g" time="2026-11-22T10:00:00Z" start="2026-11-22T10:00:00Z" '
    b'stale="2026-11-22T10:05:00Z"><point lat="65.82" lon="21.69" hae="9999999.0" '
    b'ce="9999999.0" le="9999999.0"/><detail><contact callsign="3 PLUT"/></detail></event>'
)


#: While FRIEND is current (between its start and its stale).
NOW = datetime(2026, 11, 22, 10, 1, tzinfo=UTC)


def listener(events: list[Event], uri: str = "udp://127.0.0.1:0", **options: Any) -> CotSource:
    config = CotSourceConfig(uri=uri, **options)
    return CotSource("cot", config, events.append, clock=lambda: NOW)


def at(event: bytes, time: str, uid: str = "ANDROID-1") -> bytes:
    """FRIEND for ``uid`` at ``time`` (HH:MM:SS on FRIEND's day), stale five minutes later."""
    stamp = f"2026-11-22T{time}Z".encode()
    stale = (datetime.fromisoformat(f"2026-11-22T{time}+00:00") + timedelta(minutes=5)).strftime(
        "%Y-%m-%dT%H:%M:%SZ"
    )
    return (
        event.replace(b'time="2026-11-22T10:00:00Z"', b'time="' + stamp + b'"')
        .replace(b'start="2026-11-22T10:00:00Z"', b'start="' + stamp + b'"')
        .replace(b'stale="2026-11-22T10:05:00Z"', b'stale="' + stale.encode() + b'"')
        .replace(b"ANDROID-1", uid.encode())
    )


def corpus_files() -> list[Path]:
    if not METRICS.exists():
        pytest.skip("shared corpus absent")
    return sorted(METRICS.rglob("*.xml"))


@pytest.mark.corpus
def test_real_atak_and_wintak_events_all_parse_and_no_fix_is_rejected() -> None:
    """Replayed as they arrived (the clock at each event's time), as in February 2020."""
    files = corpus_files()
    events: list[Event] = []
    now = [NOW]
    source = CotSource(
        "cot", CotSourceConfig(uri="udp://127.0.0.1:0"), events.append, clock=lambda: now[0]
    )
    for path in files:
        data = path.read_bytes()
        now[0] = parse_cot(data).time
        source.handle(data)
    assert len(files) == 887
    assert source.parsed == 887  # every real ATAK/WinTAK event passes our validator
    assert source.counts["no_fix"] == 474  # the ATAK tablet without GPS, near 0,0
    assert source.counts["accepted"] == len(events) == 265  # 228 WinTAK, 37 ATAK with a fix
    assert all(isinstance(e, BlueForce) and e.source == "cot" for e in events)
    assert all(abs(e.position.lat_deg) > 1 for e in events)  # type: ignore[union-attr]
    assert sum(source.counts.values()) == 887


@pytest.mark.corpus
def test_years_old_real_events_are_not_current_blue_force() -> None:
    """Issue 10: the 2020 captures were published as current friendly positions."""
    events: list[Event] = []
    source = CotSource("cot", CotSourceConfig(uri="udp://127.0.0.1:0"), events.append)
    for path in corpus_files():
        source.handle(path.read_bytes())
    assert events == []
    assert source.counts == {"stale": 739, "not_friendly": 148}


@pytest.mark.corpus
def test_real_events_out_of_order_keep_the_newest_per_uid() -> None:
    """Newest first (a relay's backlog after a reconnect): each unit's newest event only."""
    parsed = [(parse_cot(p.read_bytes()), p.read_bytes()) for p in corpus_files()]
    newest_first = sorted(parsed, key=lambda item: item[0].time, reverse=True)
    last = newest_first[0][0].time
    events: list[Event] = []
    source = CotSource(
        "cot", CotSourceConfig(uri="udp://127.0.0.1:0"), events.append, clock=lambda: last
    )
    for _, data in newest_first:
        source.handle(data)
    current = {
        cot.uid: cot.time
        for cot, _ in parsed
        if cot.type.startswith("a-f-") and cot.stale > last and abs(cot.lat) >= NO_FIX_DEG
    }
    newest = {}
    for cot, _ in parsed:
        if cot.uid in current:
            newest[cot.uid] = max(newest.get(cot.uid, cot.time), cot.time)
    assert sorted((e.uid, e.time) for e in events) == sorted(newest.items())  # type: ignore[union-attr]
    assert source.counts["older"] > 0


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
    # Anyone who reaches the port may send: never more than unauthenticated.
    assert event.provenance is Provenance.UNAUTHENTICATED
    assert event.source_name == "cot"


def test_a_callsign_is_made_safe_at_the_source() -> None:
    events: list[Event] = []
    hostile = FRIEND.replace(b'callsign="3 PLUT"', 'callsign="WEAPONS\u202e FREE\u200b!"'.encode())
    listener(events).handle(hostile)
    (event,) = events
    assert isinstance(event, BlueForce)
    assert event.callsign == "WEAPONS FREE?"


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
    source = listener(events, "udp+multicast://239.2.3.1:0", interface="127.0.0.1")
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
    source = listener(events, "tcp://127.0.0.1:0", max_event_bytes=1024, max_clients=1)
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
    """At the cap, a client that sent whole events keeps its place; the newcomer is closed."""
    events: list[Event] = []
    source = listener(events, "tcp://127.0.0.1:0", max_clients=1)
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
    assert source.connections["refused"] == 1


@pytest.mark.anyio
async def test_idle_strangers_holding_every_slot_do_not_lock_out_a_tak_client() -> None:
    """Squatters that never send a whole event are evicted for a client that does."""
    events: list[Event] = []
    source = listener(events, "tcp://127.0.0.1:0", max_clients=3)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            squatters = [await anyio.connect_tcp("127.0.0.1", source.local_port) for _ in range(3)]
            for squatter in squatters:
                await squatter.send(b"<")
            await eventually(lambda: source._stream.active == 3)
            async with await anyio.connect_tcp("127.0.0.1", source.local_port) as client:
                await client.send(FRIEND)
                await eventually(lambda: bool(events))
            for squatter in squatters:
                await squatter.aclose()
            tg.cancel_scope.cancel()
    assert source.connections["evicted"] == 1


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
    gateway = Gateway(config, sinks={"mem": mem}, clock=lambda: NOW)
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


class TestCurrency:
    """Only current positions, and per unit only its newest, become blue force."""

    def test_an_event_past_its_stale_is_refused_and_counted(self) -> None:
        events: list[Event] = []
        source = listener(events)
        source.handle(at(FRIEND, "09:00:00"))  # stale at 09:05, and it is 10:01
        source.handle(FRIEND)
        assert [e.uid for e in events] == ["ANDROID-1"]  # type: ignore[union-attr]
        assert source.counts == {"stale": 1, "accepted": 1}

    def test_an_older_event_never_overwrites_a_newer_one(self) -> None:
        events: list[Event] = []
        source = listener(events)
        source.handle(at(FRIEND, "10:00:30"))
        source.handle(at(FRIEND, "10:00:10"))  # relayed late
        source.handle(at(FRIEND, "10:00:30"))  # the same report via another path
        source.handle(at(FRIEND, "10:00:40"))
        assert [e.time.second for e in events] == [30, 40]
        assert source.counts == {"accepted": 2, "older": 1, "duplicate": 1}

    def test_an_event_from_the_future_cannot_lock_its_unit_out(self) -> None:
        """The clock is 10:01; an event at 23:00 would make every genuine report "older"."""
        events: list[Event] = []
        source = listener(events)
        source.handle(at(FRIEND, "23:00:00"))
        source.handle(at(FRIEND, "10:01:30"))  # within a minute ahead: clocks drift
        source.handle(at(FRIEND, "10:01:40"))
        assert [e.time.second for e in events] == [30, 40]  # type: ignore[union-attr]
        assert source.counts == {"future": 1, "accepted": 2}

    def test_remembered_units_are_bounded(self) -> None:
        events: list[Event] = []
        source = listener(events, max_uids=2)
        for n in range(5):
            source.handle(at(FRIEND, "10:00:30", uid=f"U{n}"))
        source.handle(at(FRIEND, "10:00:10", uid="U0"))  # forgotten: taken, nothing to compare
        source.handle(at(FRIEND, "10:00:10", uid="U4"))  # remembered: refused
        assert len(source._newest) == 2
        assert source.counts == {"accepted": 6, "older": 1}

    def test_a_mesh_takcontrol_is_counted_as_control_not_invalid(self) -> None:
        from sinks.cot.codec import tak_control
        from sinks.cot.proto import mesh_frame

        events: list[Event] = []
        source = listener(events)
        source.handle(mesh_frame(tak_control()))
        assert source.counts == {"control": 1}
        assert not source.problems


class TestEventSplitter:
    """A stream is cut after each ``</event>`` and resynchronised on the event's start."""

    def test_a_bare_detail_fragment_costs_only_itself(self) -> None:
        splitter = EventSplitter(16384)
        fragment = b'<detail><contact callsign="X"/></detail>'
        (event,) = splitter.feed(fragment + FRIEND)
        assert event == FRIEND
        assert splitter.fragments == 1

    def test_events_split_across_chunks_and_junk_between(self) -> None:
        splitter = EventSplitter(16384)
        stream = FRIEND + b"\n</event>garbage" + FRIEND + FRIEND[:50]
        first = splitter.feed(stream[:100])
        rest = splitter.feed(stream[100:])
        assert first == []
        assert rest == [FRIEND, FRIEND]
        assert splitter.fragments == 2  # the stray </event> and "garbage"
        assert splitter.feed(FRIEND[50:]) == [FRIEND]


@pytest.mark.anyio
async def test_tcp_fragment_before_an_event_is_counted_and_the_event_taken() -> None:
    """Issue 10: a bare <detail> on a stream swallowed the next event, uncounted."""
    events: list[Event] = []
    source = listener(events, "tcp://127.0.0.1:0")
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            async with await anyio.connect_tcp("127.0.0.1", source.local_port) as stream:
                await stream.send(b'<detail><contact callsign="X"/></detail>' + FRIEND)
                await eventually(lambda: bool(events))
            tg.cancel_scope.cancel()
    assert [e.uid for e in events] == ["ANDROID-1"]  # type: ignore[union-attr]
    assert source.counts == {"fragment": 1, "accepted": 1}


@pytest.mark.anyio
async def test_an_idle_tcp_client_is_closed_and_counted() -> None:
    events: list[Event] = []
    source = listener(events, "tcp://127.0.0.1:0", idle_timeout_s=0.2)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            async with await anyio.connect_tcp("127.0.0.1", source.local_port) as stream:
                await stream.send(FRIEND)
                with pytest.raises((anyio.EndOfStream, anyio.BrokenResourceError)):
                    await stream.receive()  # the listener hung up on the silent client
            tg.cancel_scope.cancel()
    assert source.connections == {"idle_closed": 1}
    assert source.counts == {"accepted": 1}


@pytest.mark.anyio
async def test_out_of_file_descriptors_degrades_the_listener_not_the_daemon() -> None:
    """EMFILE on accept (a real one, under a lowered RLIMIT_NOFILE) is counted and survived."""
    resource = pytest.importorskip("resource")
    events: list[Event] = []
    source = listener(events, "tcp://127.0.0.1:0")
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    fillers: list[int] = []
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            highest = max(int(fd) for fd in os.listdir("/proc/self/fd"))
            resource.setrlimit(resource.RLIMIT_NOFILE, (highest + 8, hard))
            try:
                with contextlib.suppress(OSError):
                    while True:
                        fillers.append(os.open(os.devnull, os.O_RDONLY))
                os.close(fillers.pop())  # room for exactly the client's socket
                client = socket.create_connection(("127.0.0.1", source.local_port))
                await eventually(lambda: source.connections["accept_failed"] >= 2)
            finally:
                for fd in fillers:
                    os.close(fd)
                resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
            with client:
                client.sendall(FRIEND)
                await eventually(lambda: bool(events))  # the queued client is served after all
            tg.cancel_scope.cancel()
    assert source.counts == {"accepted": 1}
