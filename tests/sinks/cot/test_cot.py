"""The CoT sink on real sockets: UDP unicast and multicast, TCP and TLS to a TAK-like server."""

from __future__ import annotations

import contextlib
import socket
import ssl
import struct
from collections.abc import AsyncIterator
from datetime import timedelta
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlparse

import anyio
import anyio.abc
import pytest
import trustme
from anyio.streams.tls import TLSListener
from pydantic import ValidationError
from test_cot_event import DETECTION, EVENTS, TELEMETRY, TRACK

from gateway.c2.sinkrunner import SinkRunner
from gateway.config import SinkEntry
from gateway.domain import sidc, symbols
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import Position
from gateway.ops.instruments import Instruments
from gateway.testing import eventually
from sinks.cot.proto import read_varint, stream_frame
from sinks.cot.sink import CotSink, CotSinkConfig
from sinks.cot.validate import parse_cot

takproto = pytest.importorskip("takproto")

UIDS = ["fischer-F26E-007", "fischer-det-d1", "fischer-trk-2026-000042"]


def sink(*destinations: Any, **extra: Any) -> CotSink:
    return CotSink("cot", CotSinkConfig.model_validate({"destinations": destinations, **extra}))


def control(kind: str, detail: str) -> bytes:
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n<event version="2.0" uid="protouid" '
        f'type="t-x-takp-{kind}" time="2026-11-22T10:00:00Z" start="2026-11-22T10:00:00Z" '
        'stale="2026-11-22T10:01:00Z" how="m-g"><point lat="0.0" lon="0.0" hae="0.0" '
        f'ce="999999" le="999999"/><detail><TakControl>{detail}</TakControl></detail></event>'
    ).encode()


OFFER = control("v", '<TakProtocolSupport version="1"/>')
RELAYED = control("x", "").replace(b"t-x-takp-x", b"a-f-G-U-C")  # another client's position


def xml_events(data: bytes) -> list[bytes]:
    return [part + b"</event>" for part in data.split(b"</event>")[:-1]]


def stream_frames(data: bytes) -> list[bytes]:
    frames, pos = [], 0
    while pos < len(data):
        assert data[pos] == 0xBF
        length, pos = read_varint(data, pos + 1)
        frames.append(stream_frame(data[pos : pos + length]))
        pos += length
    return frames


class Connection:
    """What one client sent: XML before the switch, protobuf after."""

    def __init__(self) -> None:
        self.xml = bytearray()
        self.proto = bytearray()
        self.requested_after_offer: bool | None = None


class TakServer:
    """A TAK-server-like peer: plain or TLS (client certificate required), and TAK protocol v1.

    ``offer``: send the TakControl offer on connect, after the client's first event, or never.
    ``respond``: the TakResponse status to send, or None to never answer the request.
    """

    def __init__(
        self,
        *,
        offer: Literal["connect", "late", "never"] = "never",
        respond: str | None = "true",
        tls: ssl.SSLContext | None = None,
        hang_up_after_events: int | None = None,
    ) -> None:
        self.offer, self.respond, self.tls = offer, respond, tls
        self.hang_up_after_events = hang_up_after_events
        self.connections: list[Connection] = []
        self.port = 0

    def conn(self, index: int) -> Connection:
        """Connection ``index``, or an empty one while it has not arrived."""
        return self.connections[index] if len(self.connections) > index else Connection()

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        tcp = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=0)
        self.port = tcp.extra(anyio.abc.SocketAttribute.local_port)
        listener: anyio.abc.Listener[Any] = tcp
        if self.tls is not None:
            listener = TLSListener(tcp, self.tls, standard_compatible=False)
        task_status.started()
        async with listener:
            await listener.serve(self.handle)

    async def handle(self, stream: anyio.abc.ByteStream) -> None:
        conn = Connection()
        self.connections.append(conn)
        offered = self.offer == "connect"
        async with stream:
            if offered:
                await stream.send(RELAYED + OFFER)
            try:
                async for chunk in stream:
                    if conn.requested_after_offer and self.respond == "true":
                        conn.proto += chunk
                        continue
                    conn.xml += chunk
                    if self.offer == "late" and not offered and b"</event>" in conn.xml:
                        offered = True
                        await stream.send(OFFER)
                    if conn.requested_after_offer is None and b"t-x-takp-q" in conn.xml:
                        conn.requested_after_offer = offered
                        end = conn.xml.find(b"</event>", conn.xml.find(b"t-x-takp-q")) + 8
                        conn.proto += conn.xml[end:]
                        del conn.xml[end:]
                        if self.respond is not None:
                            detail = f'<TakResponse status="{self.respond}"/>'
                            await stream.send(control("r", detail))
                    limit = self.hang_up_after_events
                    if limit is not None and conn.xml.count(b"</event>") >= limit:
                        return
            except (anyio.BrokenResourceError, ssl.SSLError, OSError):
                return


@pytest.fixture
def pki(tmp_path: Path) -> tuple[trustme.CA, ssl.SSLContext, dict[str, str]]:
    """A CA, a server context demanding client certificates, and the client's PEM files."""
    ca = trustme.CA()
    server = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ca.issue_cert("tak.example.test", "127.0.0.1").configure_cert(server)
    ca.configure_trust(server)
    server.verify_mode = ssl.CERT_REQUIRED  # TAK servers demand a client certificate
    ca.cert_pem.write_to_path(str(tmp_path / "ca.pem"))
    ca.issue_cert("fischer-gateway").private_key_and_cert_chain_pem.write_to_path(
        str(tmp_path / "client.pem")
    )
    return (
        ca,
        server,
        {"ca_file": str(tmp_path / "ca.pem"), "cert_file": str(tmp_path / "client.pem")},
    )


@contextlib.asynccontextmanager
async def serving(server: TakServer) -> AsyncIterator[int]:
    """Run ``server`` for the body of the block; yields its port."""
    async with anyio.create_task_group() as tg:
        await tg.start(server.run)
        yield server.port
        tg.cancel_scope.cancel()


def received_uids(conn: Connection) -> list[str]:
    """Our events on one connection, XML ones first, control events left out."""
    xml = [parse_cot(e.strip()).uid for e in xml_events(bytes(conn.xml)) if b"t-x-takp" not in e]
    proto = [
        takproto.parse_proto(bytearray(f)).cotEvent.uid for f in stream_frames(bytes(conn.proto))
    ]
    return xml + proto


class TestUdp:
    """Unicast and multicast datagrams: one event each, XML or mesh protobuf."""

    @pytest.mark.anyio
    async def test_pytak_receives_the_events(self) -> None:
        pytak = pytest.importorskip("pytak")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        reader, _ = await pytak.create_udp_client(urlparse(f"udp+ro://127.0.0.1:{port}"))
        cot = sink(f"udp://127.0.0.1:{port}")
        try:
            with anyio.fail_after(10):
                await cot.open()
                await cot.send(list(EVENTS))
                received = [(await reader.recv())[0] for _ in range(3)]
        finally:
            await cot.aclose()
            reader.close()
        assert [parse_cot(data, strict=True).uid for data in received] == UIDS

    @pytest.mark.anyio
    async def test_mesh_protobuf_over_loopback_multicast(self) -> None:
        """Multicast on the loopback interface (IP_MULTICAST_IF 127.0.0.1, loop on)."""
        group = "239.2.3.1"
        receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        receiver.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        receiver.bind((group, 0))
        port = receiver.getsockname()[1]
        try:
            membership = struct.pack("4s4s", socket.inet_aton(group), socket.inet_aton("127.0.0.1"))
            receiver.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
        except OSError as exc:
            receiver.close()
            pytest.skip(f"this host cannot join a multicast group on loopback: {exc}")
        receiver.setblocking(False)
        cot = sink(f"udp+multicast://{group}:{port}?ttl=1&iface=127.0.0.1", protocol="protobuf")
        try:
            with anyio.fail_after(10):
                await cot.open()
                await cot.send([TELEMETRY])
                await anyio.wait_readable(receiver)
                data = receiver.recv(65536)
        finally:
            await cot.aclose()
            receiver.close()
        assert data.startswith(b"\xbf\x01\xbf")
        assert takproto.parse_proto(bytearray(data)).cotEvent.uid == UIDS[0]

    @pytest.mark.anyio
    async def test_tracks_go_on_change(self) -> None:
        """An unchanged track waits for its refresh; a moved one goes at once."""
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver:
            receiver.bind(("127.0.0.1", 0))
            receiver.setblocking(False)
            cot = sink(f"udp://127.0.0.1:{receiver.getsockname()[1]}", track_refresh_s=60)
            later = TRACK.time + timedelta(seconds=30)
            moved = TRACK.model_copy(
                update={"time": later, "position": Position(lat_deg=58.5, lon_deg=15.6)}
            )
            batches = [
                [TRACK],
                [TRACK.model_copy(update={"time": later})],  # unchanged: skipped
                [moved],
                [moved.model_copy(update={"time": later + timedelta(seconds=61)})],  # refresh
            ]
            got = []
            with anyio.fail_after(10):
                await cot.open()
                for batch in batches:
                    await cot.send(batch)
                await cot.send([TELEMETRY])  # a marker: everything before it has arrived
                while not got or parse_cot(got[-1]).uid != UIDS[0]:
                    await anyio.wait_readable(receiver)
                    got.append(receiver.recv(65536))
                await cot.aclose()
        assert [parse_cot(d).lat for d in got] == [
            TRACK.position.lat_deg,
            58.5,
            58.5,
            TELEMETRY.position.lat_deg,
        ]  # type: ignore[union-attr]

    @pytest.mark.anyio
    async def test_a_failed_track_is_not_taken_as_delivered(self) -> None:
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        cot = sink(f"tcp://127.0.0.1:{port}", connect_timeout_s=2)
        with anyio.fail_after(10):
            for _ in range(2):  # the retry is not skipped as "unchanged"
                with pytest.raises(TransientSinkError, match=f"tcp://127.0.0.1:{port}"):
                    await cot.send([TRACK])
            await cot.aclose()
        assert cot._delivered == {}

    @pytest.mark.anyio
    async def test_delivered_tracks_are_forgotten_once_past_their_stale_time(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver:
            receiver.bind(("127.0.0.1", 0))
            cot = sink(f"udp://127.0.0.1:{receiver.getsockname()[1]}", stale={"track_s": 60})
            with anyio.fail_after(10):
                for n in range(30):  # a new track every 10 s: each stale 60 s later
                    track = TRACK.model_copy(
                        update={
                            "track_id": f"2026-{n:06d}",
                            "time": TRACK.time + timedelta(seconds=10 * n),
                        }
                    )
                    await cot.send([track])
                await cot.aclose()
        # The last 60 s of tracks, and at most the 10 s scan interval's more.
        assert 6 <= len(cot._delivered) <= 8


class TestStreams:
    """TAK server streams: XML framing, TLS with client certificates, TAK protocol v1."""

    @pytest.mark.anyio
    async def test_tcp_xml_stream_has_nothing_after_each_event(self) -> None:
        server = TakServer()
        with anyio.fail_after(10):
            async with serving(server) as port:
                cot = sink(f"tcp://127.0.0.1:{port}")
                await cot.open()
                await cot.send(list(EVENTS))
                expected = b"".join(e.get("xml") for e in _encoded(cot, EVENTS))
                await eventually(lambda: len(server.conn(0).xml) >= len(expected))
                await cot.aclose()
        assert bytes(server.connections[0].xml) == expected
        assert all(e.endswith(b"</event>") for e in xml_events(expected))

    @pytest.mark.anyio
    async def test_tls_negotiates_protobuf_after_the_offer(
        self, pki: tuple[trustme.CA, ssl.SSLContext, dict[str, str]]
    ) -> None:
        _, server_tls, files = pki
        server = TakServer(offer="connect", tls=server_tls)
        with anyio.fail_after(15):
            async with serving(server) as port:
                tls = {**files, "server_hostname": "tak.example.test"}
                cot = sink({"uri": f"tls://127.0.0.1:{port}", "tls": tls}, protocol="negotiate")
                await cot.open()
                assert cot._transports[0].mode == "protobuf"  # type: ignore[union-attr]
                await cot.send(list(EVENTS))
                await eventually(lambda: len(stream_frames_safe(server.conn(0).proto)) == 3)
                await cot.aclose()
        conn = server.connections[0]
        assert conn.requested_after_offer is True
        assert xml_events(bytes(conn.xml))[0].count(b"t-x-takp-q") == 1  # only the request
        assert received_uids(conn) == UIDS

    @pytest.mark.anyio
    async def test_a_late_offer_switches_the_stream_mid_way(self) -> None:
        server = TakServer(offer="late")
        with anyio.fail_after(15):
            async with serving(server) as port:
                cot = sink(f"tcp://127.0.0.1:{port}", protocol="negotiate", offer_wait_s=0)
                await cot.open()
                await cot.send([TELEMETRY])  # XML: no offer yet
                await eventually(lambda: b"</event>" in server.conn(0).xml)
                await cot.send([DETECTION])  # sees the offer, asks, switches, then sends
                await eventually(lambda: len(stream_frames_safe(server.conn(0).proto)) == 1)
                await cot.aclose()
        assert received_uids(server.connections[0]) == UIDS[:2]
        assert server.connections[0].requested_after_offer is True

    @pytest.mark.anyio
    async def test_a_refused_request_stays_on_xml(self) -> None:
        server = TakServer(offer="connect", respond="false")
        with anyio.fail_after(15):
            async with serving(server) as port:
                cot = sink(f"tcp://127.0.0.1:{port}", protocol="negotiate")
                await cot.open()
                await cot.send([TELEMETRY])
                await eventually(lambda: server.conn(0).xml.count(b"</event>") == 2)
                await cot.aclose()
        assert received_uids(server.connections[0]) == UIDS[:1]
        assert not server.connections[0].proto

    @pytest.mark.anyio
    async def test_no_response_ends_the_connection_and_xml_is_used_after(self) -> None:
        server = TakServer(offer="connect", respond=None)
        with anyio.fail_after(15):
            async with serving(server) as port:
                cot = sink(f"tcp://127.0.0.1:{port}", protocol="negotiate", response_wait_s=0.2)
                with pytest.raises(TransientSinkError, match=r"no TakResponse within 0\.2 s"):
                    await cot.open()
                await cot.open()  # the retry: connects again and does not ask
                await cot.send([TELEMETRY])
                await eventually(
                    lambda: (
                        len(server.connections) == 2 and b"</event>" in server.connections[1].xml
                    )
                )
                await cot.aclose()
        assert b"t-x-takp-q" not in server.connections[1].xml
        assert received_uids(server.connections[1]) == UIDS[:1]

    @pytest.mark.anyio
    async def test_a_server_that_hangs_up_is_reconnected(self) -> None:
        server = TakServer(hang_up_after_events=1)
        with anyio.fail_after(15):
            async with serving(server) as port:
                cot = sink(f"tcp://127.0.0.1:{port}")
                await cot.open()
                await cot.send([TELEMETRY])
                await eventually(lambda: cot._transports[0]._sock is not None and _peer_closed(cot))
                await cot.send([DETECTION])  # notices the EOF first, reconnects, delivers
                await eventually(
                    lambda: (
                        len(server.connections) == 2 and b"</event>" in server.connections[1].xml
                    )
                )
                await cot.aclose()
        assert [received_uids(c) for c in server.connections] == [UIDS[:1], UIDS[1:2]]

    @pytest.mark.anyio
    async def test_pkcs12_client_certificate_with_password_file(
        self, tmp_path: Path, pki: tuple[trustme.CA, ssl.SSLContext, dict[str, str]]
    ) -> None:
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.serialization import pkcs12

        ca, server_tls, files = pki
        leaf = ca.issue_cert("fischer-gateway")
        key = serialization.load_pem_private_key(leaf.private_key_pem.bytes(), None)
        cert = x509.load_pem_x509_certificate(leaf.cert_chain_pems[0].bytes())
        encryption = serialization.BestAvailableEncryption(b"s3cret")
        bundle = pkcs12.serialize_key_and_certificates(b"gw", key, cert, None, encryption)  # type: ignore[arg-type]
        (tmp_path / "client.p12").write_bytes(bundle)
        (tmp_path / "p12.pass").write_text("s3cret\n")
        tls = {"ca_file": files["ca_file"], "pkcs12_file": str(tmp_path / "client.p12"),
               "password_file": str(tmp_path / "p12.pass")}  # fmt: skip
        server = TakServer(tls=server_tls)
        with anyio.fail_after(15):
            async with serving(server) as port:
                cot = sink({"uri": f"tls://127.0.0.1:{port}", "tls": tls})
                await cot.open()
                await cot.send([TELEMETRY])
                await eventually(
                    lambda: bool(server.connections) and b"</event>" in server.connections[0].xml
                )
                await cot.aclose()
        assert received_uids(server.connections[0]) == UIDS[:1]

    @pytest.mark.parametrize(
        ("change", "message"),
        [
            ({"ca_file": "other-ca.pem"}, r"not trusted by the pinned CA .*other-ca\.pem"),
            (
                {"server_hostname": "evil.example.test"},
                "not valid for hostname 'evil.example.test'",
            ),
            ({"password_file": "wrong.pass", "cert_file": "client.p12"}, "cannot"),
        ],
    )
    @pytest.mark.anyio
    async def test_wrong_ca_or_hostname_is_refused_with_a_clear_error(
        self, tmp_path: Path, pki: tuple[trustme.CA, ssl.SSLContext, dict[str, str]],
        change: dict[str, str], message: str,
    ) -> None:  # fmt: skip
        _, server_tls, files = pki
        trustme.CA().cert_pem.write_to_path(str(tmp_path / "other-ca.pem"))
        (tmp_path / "wrong.pass").write_text("nope")
        (tmp_path / "client.p12").write_bytes(b"not pkcs12")
        paths = {k: (v if k == "server_hostname" else str(tmp_path / v)) for k, v in change.items()}
        server = TakServer(tls=server_tls)
        with anyio.fail_after(15):
            async with serving(server) as port:
                cot = sink({"uri": f"tls://127.0.0.1:{port}", "tls": {**files, **paths}})
                with pytest.raises(TransientSinkError, match=message) as caught:
                    await cot.open()
                await cot.aclose()
        assert caught.value.sink == "cot"
        assert f"tls://127.0.0.1:{port}" in str(caught.value)
        assert "s3cret" not in str(caught.value)
        assert not any(c.xml for c in server.connections)

    @pytest.mark.anyio
    async def test_a_server_refusing_our_certificate_fails_the_send(
        self, tmp_path: Path, pki: tuple[trustme.CA, ssl.SSLContext, dict[str, str]]
    ) -> None:
        _, server_tls, files = pki
        stranger = trustme.CA().issue_cert("someone-else")
        stranger.private_key_and_cert_chain_pem.write_to_path(str(tmp_path / "stranger.pem"))
        server = TakServer(offer="connect", tls=server_tls)
        with anyio.fail_after(15):
            async with serving(server) as port:
                tls = {**files, "cert_file": str(tmp_path / "stranger.pem")}
                cot = sink({"uri": f"tls://127.0.0.1:{port}", "tls": tls}, protocol="negotiate")
                with pytest.raises(TransientSinkError, match=r"TLS|certificate|closed"):  # noqa: PT012 - the refusal may come at open or at the first send
                    await cot.open()
                    await cot.send([TELEMETRY])
                await cot.aclose()
        assert not any(c.xml or c.proto for c in server.connections)

    @pytest.mark.anyio
    async def test_unreachable_server_is_transient_and_named(self) -> None:
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        cot = sink(f"tcp://127.0.0.1:{port}")
        with (
            anyio.fail_after(10),
            pytest.raises(TransientSinkError, match="cannot connect") as caught,
        ):
            await cot.open()
        await cot.aclose()
        assert f"sink cot: tcp://127.0.0.1:{port}" in str(caught.value)

    @pytest.mark.anyio
    async def test_runs_under_the_sink_runner(self) -> None:
        """The real runner drives open/send/aclose under its own deadlines and cancel scopes."""
        server = TakServer(offer="connect")
        with anyio.fail_after(15):
            async with serving(server) as port, anyio.create_task_group() as tg:
                cot = sink(f"tcp://127.0.0.1:{port}", protocol="negotiate")
                runner = SinkRunner(SinkEntry(name="cot", type="cot"), cot, Instruments())
                await tg.start(runner.run)
                runner.offer(TELEMETRY, 0.0)
                runner.offer(TRACK, 0.0)
                await eventually(lambda: len(stream_frames_safe(server.conn(0).proto)) == 2)
                runner.stop()
                await runner.wait_done()
        assert received_uids(server.connections[0]) == [UIDS[0], UIDS[2]]
        assert runner.status()["state"] == "closed"


def _encoded(cot: CotSink, events: tuple[Any, ...]) -> list[Any]:
    from sinks.cot.codec import Encoded
    from sinks.cot.event import build

    return [Encoded(c) for e in events if (c := build(e, cot.options)) is not None]


def _peer_closed(cot: CotSink) -> bool:
    sock = cot._transports[0]._sock  # type: ignore[union-attr]
    assert sock is not None
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False


def stream_frames_safe(data: bytes | bytearray) -> list[bytes]:
    try:
        return stream_frames(bytes(data))
    except (AssertionError, IndexError, ValueError):
        return []


class TestConfig:
    """Destinations are validated when the config loads, with messages naming the URI."""

    def test_uris_with_options(self) -> None:
        config = CotSinkConfig.model_validate(
            {"destinations": ["udp+multicast://239.2.3.1:6969?ttl=3&iface=eth0", "tcp://tak:8087"]}
        )
        mesh, stream = (d.endpoint("negotiate") for d in config.destinations)
        assert (mesh.ttl, mesh.interface, mesh.protocol) == (3, "eth0", "xml")
        assert (stream.host, stream.port, stream.protocol) == ("tak", 8087, "negotiate")

    @pytest.mark.parametrize(
        ("destination", "message"),
        [
            ("http://tak:8087", "expected udp://"),
            ("tcp://tak", "expected udp://"),
            ("udp+multicast://10.0.0.1:6969", "not a multicast group"),
            ("tcp://tak:8087?ttl=2", "only udp URIs take query options"),
            ("tls://tak:8089", "a 'tls' section goes with tls://"),
            ({"uri": "udp://h:1", "protocol": "negotiate"}, "negotiate is for tcp"),
            ("tcp://user:pw@tak:8087", "no passwords in URIs"),
            ({"uri": "tls://t:1", "tls": {"ca_file": "ca.pem"}}, "exactly one of cert_file"),
        ],
    )
    def test_bad_destinations_are_named(self, destination: Any, message: str) -> None:
        with pytest.raises(ValidationError, match=message):
            CotSinkConfig.model_validate({"destinations": [destination]})

    def test_stale_per_kind_is_checked(self) -> None:
        with pytest.raises(ValidationError, match="Extra inputs"):
            CotSinkConfig.model_validate({"destinations": ["udp://h:1"], "stale": {"tracks_s": 5}})
        config = CotSinkConfig.model_validate(
            {"destinations": ["udp://h:1"], "stale": {"track_s": 60}}
        )
        assert (config.stale.telemetry_s, config.stale.track_s) == (15.0, 60.0)

    def test_link_state_may_be_routed_and_is_ignored(self) -> None:
        kinds = ["telemetry", "link_state"]
        assert CotSinkConfig.model_validate({"destinations": ["udp://h:1"], "kinds": kinds})
        with pytest.raises(ValidationError, match="not"):
            CotSinkConfig.model_validate({"destinations": ["udp://h:1"], "kinds": ["handoff"]})

    def test_a_partial_stale_table_is_completed_at_load(self) -> None:
        """Issue 10: a partial stale table must not reach ``send`` as a KeyError."""
        with pytest.raises(ValidationError, match="Extra inputs"):
            CotSinkConfig.model_validate(
                {"destinations": ["udp://h:1"], "stale": {"telemetry": 10}}
            )
        cot = sink("udp://h:1", stale={"telemetry_s": 10})
        assert (cot.options.stale.telemetry_s, cot.options.stale.detection_s) == (10.0, 120.0)
        assert cot.options.stale.track_s == 300.0


def udp_receiver() -> socket.socket:
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind(("127.0.0.1", 0))
    receiver.setblocking(False)
    return receiver


async def datagrams(receiver: socket.socket, count: int) -> list[bytes]:
    """The next ``count`` datagrams; the caller sets the deadline."""
    received = []
    while len(received) < count:
        await anyio.wait_readable(receiver)
        received.append(receiver.recv(65536))
    return received


class TestMeshAnnouncements:
    """Mesh protobuf advertises TAK protocol v1 at least every interval (``cot.md`` §7)."""

    @pytest.mark.anyio
    async def test_an_idle_mesh_still_gets_takcontrol_from_the_sinks_lifetime(self) -> None:
        with udp_receiver() as mesh, udp_receiver() as xml:
            cot = sink(
                {"uri": f"udp://127.0.0.1:{mesh.getsockname()[1]}", "protocol": "protobuf"},
                f"udp://127.0.0.1:{xml.getsockname()[1]}",
                takcontrol_interval_s=0.2,
            )
            runner = SinkRunner(SinkEntry(name="cot", type="cot"), cot, Instruments())
            with anyio.fail_after(10):
                async with anyio.create_task_group() as tg:
                    await tg.start(runner.run)
                    idle = await datagrams(mesh, 3)  # no events at all: control on its own
                    runner.offer(TELEMETRY, 0.0)
                    (with_event,) = await datagrams(xml, 1)
                    tg.cancel_scope.cancel()
        for data in idle:
            message = takproto.parse_proto(bytearray(data))
            assert message.HasField("takControl")
            assert not message.HasField("cotEvent")
            assert (message.takControl.minProtoVersion, message.takControl.maxProtoVersion) == (
                1,
                1,
            )
        assert b"TakControl" not in with_event  # XML destinations get no protobuf control

    @pytest.mark.anyio
    async def test_takcontrol_rides_on_an_event_when_due(self) -> None:
        with udp_receiver() as mesh:
            port = mesh.getsockname()[1]
            cot = sink({"uri": f"udp://127.0.0.1:{port}", "protocol": "protobuf"})
            with anyio.fail_after(10):
                await cot.open()
                await cot.send([TELEMETRY, DETECTION])
                first, second = await datagrams(mesh, 2)
                await cot.aclose()
        carried = takproto.parse_proto(bytearray(first))
        assert carried.takControl.maxProtoVersion == 1
        assert carried.cotEvent.uid == UIDS[0]
        plain = takproto.parse_proto(bytearray(second))
        assert not plain.HasField("takControl")  # once per interval, not on every event
        assert plain.cotEvent.uid == UIDS[1]

    @pytest.mark.anyio
    async def test_udp_contact_has_no_stream_endpoint(self) -> None:
        """``*:-1:stcp`` means "reach me via the TAK server": wrong on the mesh."""
        with udp_receiver() as xml, udp_receiver() as mesh:
            cot = sink(
                f"udp://127.0.0.1:{xml.getsockname()[1]}",
                {"uri": f"udp://127.0.0.1:{mesh.getsockname()[1]}", "protocol": "protobuf"},
            )
            with anyio.fail_after(10):
                await cot.open()
                await cot.send([TELEMETRY])
                (as_xml,) = await datagrams(xml, 1)
                (as_proto,) = await datagrams(mesh, 1)
                await cot.aclose()
        assert b"<contact callsign=" in as_xml
        assert b"endpoint" not in as_xml
        message = takproto.parse_proto(bytearray(as_proto))
        assert message.cotEvent.detail.contact.callsign == "FISCHER F26E-007"
        assert message.cotEvent.detail.contact.endpoint == ""


class TestRefusals:
    """An event that cannot be delivered is refused by id; the rest of the batch goes."""

    @pytest.mark.anyio
    async def test_an_event_too_large_for_a_datagram_is_refused_alone(self) -> None:
        huge = DETECTION.model_copy(update={"event_id": "big", "subtype": "x" * 70_000})
        with udp_receiver() as receiver:
            cot = sink(f"udp://127.0.0.1:{receiver.getsockname()[1]}")
            with anyio.fail_after(10):
                await cot.open()
                with pytest.raises(PermanentSinkError) as caught:
                    await cot.send([TELEMETRY, huge, TRACK])
                received = await datagrams(receiver, 2)
                await cot.aclose()
        assert caught.value.event_ids == frozenset({"big"})
        assert [parse_cot(d).uid for d in received] == [UIDS[0], UIDS[2]]


@pytest.mark.anyio
async def test_opening_the_sink_reads_the_symbol_tables_before_the_first_event() -> None:
    # Parsing them takes milliseconds: at the first detection it would delay its picture.
    for cached in (symbols._table, symbols._own_by_mav_type, sidc._table):
        cached.cache_clear()
    sink = CotSink("cot", CotSinkConfig.model_validate({"destinations": ["udp://127.0.0.1:9"]}))
    await sink.open()
    try:
        for cached in (symbols._table, symbols._own_by_mav_type, sidc._table):
            assert cached.cache_info().currsize == 1, cached
    finally:
        await sink.aclose()
