"""The NFFI sink against real peers: an IP1 TCP server, a TLS server that demands a client
certificate (trustme), and a file; documents checked by our parser (the XSD checks are in
test_nffi_codec.py and the e2e tests)."""

from __future__ import annotations

import contextlib
import ssl
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import anyio
import anyio.abc
import pytest
import trustme
from anyio.streams.tls import TLSListener
from pydantic import ValidationError

from gateway.contract import check_sink
from gateway.errors import TransientSinkError
from gateway.events import BlueForce, Position, Telemetry, Velocity
from sinks.nffi.codec import parse_message
from sinks.nffi.sink import NffiSink, NffiSinkConfig
from sinks.nffi.stream import MessageSplitter

pytestmark = pytest.mark.anyio
T0 = datetime(2026, 11, 22, 10, 15, 30, tzinfo=UTC)


def telemetry(airframe: str = "F26E-001", at: datetime = T0) -> Telemetry:
    return Telemetry(
        event_id=f"t-{airframe}-{at.timestamp()}",
        airframe=airframe,
        time=at,
        position=Position(lat_deg=58.41, lon_deg=15.62, alt_msl_m=600.0),
        velocity=Velocity(north_mps=10.0, east_mps=0.0, down_mps=0.0),
    )


def friend(at: datetime = T0) -> BlueForce:
    return BlueForce(
        event_id="b-1",
        uid="ANDROID-1",
        time=at,
        callsign="3 PLUT",
        position=Position(lat_deg=58.415, lon_deg=15.64),
        source="cot",
        speed_mps=1.5,
    )


@dataclass
class Peer:
    """An IP1 receiver: splits what arrives into documents; may hang up after the first."""

    tls: ssl.SSLContext | None = None
    hang_up_after_first: bool = False
    port: int = 0
    documents: list[bytes] = field(default_factory=list)
    connections: int = 0
    hung_up: anyio.Event = field(default_factory=anyio.Event)
    _arrived: anyio.Event = field(default_factory=anyio.Event)

    async def run(self, *, task_status: anyio.abc.TaskStatus[None]) -> None:
        tcp = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=0)
        self.port = tcp.extra(anyio.abc.SocketAttribute.local_port)
        listener: anyio.abc.Listener[Any] = tcp
        if self.tls is not None:
            listener = TLSListener(tcp, self.tls, standard_compatible=False)
        task_status.started()
        async with listener:
            await listener.serve(self.handle)

    async def handle(self, stream: anyio.abc.ByteStream) -> None:
        self.connections += 1
        splitter = MessageSplitter(1 << 20)
        first = self.connections == 1
        with contextlib.suppress(anyio.BrokenResourceError, ssl.SSLError, OSError):
            async with stream:
                async for chunk in stream:
                    self.documents += splitter.feed(chunk)
                    self._arrived.set()
                    if self.hang_up_after_first and first and self.documents:
                        break
        if first:
            self.hung_up.set()  # closed: our FIN is on its way over loopback

    async def wait_for(self, count: int) -> None:
        with anyio.fail_after(10):
            while len(self.documents) < count:
                self._arrived = anyio.Event()
                await self._arrived.wait()


def sink(**options: Any) -> NffiSink:
    return NffiSink("nffi-test", NffiSinkConfig.model_validate(options))


class TestConfig:
    def test_needs_a_destination(self) -> None:
        with pytest.raises(ValidationError, match=r"uri .* path"):
            NffiSinkConfig.model_validate({})

    def test_refuses_other_schemes_kinds_and_bad_identities(self, tmp_path: Path) -> None:
        for options, match in [
            ({"uri": "udp://h:1"}, "tcp://HOST:PORT"),
            ({"path": "x", "kinds": ["detection"]}, "telemetry and blue_force"),
            ({"path": "x", "country": "Sweden"}, "pattern"),
            ({"path": "x", "system": "FISCHER GW"}, "pattern"),
            ({"uri": "tls://h:1"}, "'tls' section"),
        ]:
            with pytest.raises(ValidationError, match=match):
                NffiSinkConfig.model_validate(options)

    def test_a_missing_ca_is_a_config_error_on_the_node(self, tmp_path: Path) -> None:
        options = {
            "uri": "tls://h:1",
            "tls": {"ca_file": str(tmp_path / "none.pem"), "cert_file": str(tmp_path / "c.pem")},
        }
        assert NffiSinkConfig.model_validate(options).tls is not None  # no files read here
        with pytest.raises(ValidationError, match=r"none\.pem"):
            NffiSinkConfig.model_validate(options, context={"environment": True})


def test_keeps_the_sink_contract(tmp_path: Path) -> None:
    check_sink(NffiSink, {"path": str(tmp_path / "out.xml")})


async def test_tracks_go_to_a_tcp_peer_and_a_file(tmp_path: Path) -> None:
    peer = Peer()
    path = tmp_path / "nffi.xml"
    async with anyio.create_task_group() as tg:
        await tg.start(peer.run)
        out = sink(uri=f"tcp://127.0.0.1:{peer.port}", path=str(path), country="SWE")
        await out.open()
        await out.send([telemetry(), friend()])
        await out.send([telemetry(at=T0 + timedelta(seconds=1))])
        await peer.wait_for(2)
        await out.aclose()
        tg.cancel_scope.cancel()
    from_file = MessageSplitter(1 << 20).feed(path.read_bytes())
    assert [d.strip() for d in from_file] == [d.strip() for d in peer.documents]
    first, second = (parse_message(d).tracks for d in peer.documents)
    assert [t.transponder_id for t in first] == ["F26E-001", "ANDROID-1"]
    assert first[1].speed_mps == pytest.approx(1.5)
    assert [t.time for t in second] == [T0 + timedelta(seconds=1)]


async def test_one_track_per_unit_and_second(tmp_path: Path) -> None:
    path = tmp_path / "nffi.xml"
    out = sink(path=str(path))
    await out.open()
    half = T0 + timedelta(milliseconds=500)
    await out.send([telemetry(), telemetry(at=half), telemetry("F26E-002")])
    await out.send([telemetry(at=half)])  # the same trackSource and dateTime again: nothing
    await out.aclose()
    (document,) = MessageSplitter(1 << 20).feed(path.read_bytes())
    tracks = parse_message(document).tracks
    assert sorted(t.transponder_id for t in tracks) == ["F26E-001", "F26E-002"]
    assert out.documents == 1


async def test_a_peer_that_hung_up_is_reconnected(tmp_path: Path) -> None:
    peer = Peer(hang_up_after_first=True)
    async with anyio.create_task_group() as tg:
        await tg.start(peer.run)
        out = sink(uri=f"tcp://127.0.0.1:{peer.port}")
        await out.open()
        await out.send([telemetry()])
        await peer.wait_for(1)
        with anyio.fail_after(5):
            await peer.hung_up.wait()
        await out.send([telemetry(at=T0 + timedelta(seconds=1))])
        await peer.wait_for(2)
        assert (peer.connections, out.reconnects) == (2, 1)
        await out.aclose()
        tg.cancel_scope.cancel()


async def test_no_peer_is_a_transient_error_naming_it() -> None:
    with anyio.fail_after(10):
        out = sink(uri="tcp://127.0.0.1:9", connect_timeout_s=2)
        with pytest.raises(TransientSinkError, match=r"nffi-test: tcp://127.0.0.1:9"):
            await out.open()
        await out.aclose()


async def test_tls_with_a_client_certificate(tmp_path: Path) -> None:
    ca = trustme.CA()
    server = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ca.issue_cert("127.0.0.1").configure_cert(server)
    ca.configure_trust(server)
    server.verify_mode = ssl.CERT_REQUIRED
    ca.cert_pem.write_to_path(str(tmp_path / "ca.pem"))
    ca.issue_cert("fischer-gateway").private_key_and_cert_chain_pem.write_to_path(
        str(tmp_path / "client.pem")
    )
    peer = Peer(tls=server)
    tls = {"ca_file": str(tmp_path / "ca.pem"), "cert_file": str(tmp_path / "client.pem")}
    async with anyio.create_task_group() as tg:
        await tg.start(peer.run)
        out = sink(uri=f"tls://127.0.0.1:{peer.port}", tls=tls)
        await out.open()
        await out.send([telemetry()])
        await peer.wait_for(1)
        await out.aclose()
        stranger = trustme.CA()
        stranger.cert_pem.write_to_path(str(tmp_path / "other.pem"))
        wrong = sink(
            uri=f"tls://127.0.0.1:{peer.port}", tls={**tls, "ca_file": str(tmp_path / "other.pem")}
        )
        with pytest.raises(TransientSinkError, match="not trusted by the pinned CA"):
            await wrong.open()
        tg.cancel_scope.cancel()
    assert parse_message(peer.documents[0]).tracks[0].transponder_id == "F26E-001"
