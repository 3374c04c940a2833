"""The CoT sink: XML and protobuf checked by independent decoders, real UDP, TCP and TLS."""

from __future__ import annotations

import contextlib
import socket
import ssl
import struct
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import anyio
import anyio.abc
import pytest
import trustme
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.cot_validate import CotError, parse_cot
from gateway.errors import TransientSinkError
from gateway.events import Detection, Position, Sensor, Telemetry, Track, Velocity
from gateway.testing import fuzz_examples
from sinks._cot_codec import mesh_frame, stream_frame, to_proto, to_xml
from sinks._cot_event import CotOptions, build
from sinks._cot_geoid import GeoidGrid
from sinks.cot import CotSink, CotSinkConfig

takproto = pytest.importorskip("takproto")
etree = pytest.importorskip("lxml.etree")

CORPUS = Path(__file__).resolve().parents[2].parent / "shared" / "corpus" / "cot"
XSD = CORPUS / "atak_civ_takcot" / "mitre" / "CoT Base-Event Schema  (PUBLIC RELEASE).xsd"
T0 = datetime(2026, 11, 22, 10, 15, 30, 250000, tzinfo=UTC)

TELEMETRY = Telemetry(
    event_id="t1",
    airframe="F26E-007",
    time=T0,
    position=Position(lat_deg=58.4108123, lon_deg=15.6214031, alt_msl_m=583.0, alt_hae_m=612.4),
    heading_deg=87.5,
    groundspeed_mps=23.1,
    battery_pct=76.0,
    h_acc_m=4.5,
    mav_type=1,
    active_link="sdr",
)
DETECTION = Detection(
    event_id="d1",
    airframe="F26E-007",
    time=T0,
    sensor=Sensor.IR,
    object_class="tank",
    subtype="T-72",
    confidence=0.91,
    position=Position(lat_deg=58.423917, lon_deg=15.650112),
    sigma_h_m=12.0,
)
TRACK = Track(
    event_id="k1",
    track_id="2026-000042",
    time=T0,
    object_class="uav",
    confidence=0.78,
    position=Position(lat_deg=58.401002, lon_deg=15.59877, alt_hae_m=245.0),
    cep50_m=20.0,
    cep90_m=36.5,
    velocity=Velocity(north_mps=10.0, east_mps=10.0, down_mps=0.0),
    detection_ids=("d1", "d2"),
    airframes=("F26E-007",),
    first_seen=T0,
    last_seen=T0,
    hostility="hostile",
)
EVENTS = [TELEMETRY, DETECTION, TRACK]


def cot_events() -> list[Any]:
    return [build(e, CotOptions()) for e in EVENTS]


class TestEncoding:
    """What each event becomes, checked by the schema, our validator and takproto."""

    def test_own_airframe_detection_and_track(self) -> None:
        own, det, trk = cot_events()
        assert (own.uid, own.type, own.how, own.hae) == (
            "fischer-F26E-007",
            "a-f-A-M-F-Q",
            "m-g",
            612.4,
        )
        assert (det.type, det.how, det.ce) == ("a-h-G-E-V-A-T", "m-i", 12.0)
        assert trk.type == "a-h-A-M-F-Q"
        assert trk.course_deg == pytest.approx(45.0)
        assert trk.ce == pytest.approx(20.0 / 1.1774, rel=1e-4)
        assert b"SHGPEVAT-------" in to_xml(det)
        assert b'relation="p-p"' in to_xml(det)

    def test_no_position_no_event(self) -> None:
        assert build(Telemetry(event_id="x", airframe="A", time=T0), CotOptions()) is None

    def test_msl_is_never_sent_as_hae(self, tmp_path: Path) -> None:
        msl_only = TELEMETRY.model_copy(
            update={"position": Position(lat_deg=58.4, lon_deg=15.6, alt_msl_m=583.0)}
        )
        assert build(msl_only, CotOptions()).hae == 9999999.0  # type: ignore[union-attr]
        grid = tmp_path / "g.gtx"
        header = struct.pack(">ddddii", 50.0, 10.0, 1.0, 1.0, 20, 20)
        grid.write_bytes(header + struct.pack(">400f", *([29.4] * 400)))
        with_geoid = build(msl_only, CotOptions(geoid=GeoidGrid(grid).undulation))
        assert with_geoid is not None
        assert with_geoid.hae == pytest.approx(583.0 + 29.4, abs=1e-4)

    @pytest.mark.parametrize("index", range(3))
    def test_xml_validates_against_the_mitre_schema(self, index: int) -> None:
        if not XSD.exists():
            pytest.skip("shared corpus absent")
        schema = etree.XMLSchema(etree.parse(str(XSD)))
        document = etree.fromstring(to_xml(cot_events()[index]))
        assert schema.validate(document), schema.error_log
        parse_cot(to_xml(cot_events()[index]))

    @pytest.mark.parametrize("index", range(3))
    def test_protobuf_decodes_in_takproto_in_both_framings(self, index: int) -> None:
        event = cot_events()[index]
        for framed in (mesh_frame(to_proto(event)), stream_frame(to_proto(event))):
            message = takproto.parse_proto(bytearray(framed))
            cot = message.cotEvent
            assert (cot.uid, cot.type, cot.how) == (event.uid, event.type, event.how)
            assert (cot.lat, cot.lon) == (event.lat, event.lon)
            assert cot.staleTime == int(event.stale.timestamp() * 1000)
        if event.callsign:
            assert message.cotEvent.detail.contact.callsign == event.callsign

    def test_xml_decodes_in_takproto(self) -> None:
        message = takproto.parse_proto(bytearray(to_xml(cot_events()[0])))
        assert message.cotEvent.detail.track.speed == pytest.approx(23.1)
        assert message.cotEvent.detail.status.battery == 76

    def test_xml_ends_at_the_event(self) -> None:
        assert to_xml(cot_events()[0]).endswith(b"</event>")


class TestValidator:
    """Our validator refuses what receivers drop and the decoders let through."""

    def test_latitude_91_is_refused_though_takproto_accepts_it(self) -> None:
        bad = to_xml(cot_events()[0]).replace(b'lat="58.4108123"', b'lat="91.0"')
        assert takproto.parse_proto(bytearray(bad)) is not None
        with pytest.raises(CotError, match="off the globe"):
            parse_cot(bad)

    @pytest.mark.parametrize(
        ("old", "new", "reason"),
        [
            (b'how="m-g"', b'how=""', "how"),
            (b'Z" start', b'+00:00" start', "UTC"),
            (b"<point", b"<nopoint", "point"),
            (b'hae="612.4"', b'hae="NaN"', "not a number"),
        ],
    )
    def test_broken_events_name_the_problem(self, old: bytes, new: bytes, reason: str) -> None:
        bad = to_xml(cot_events()[0]).replace(old, new, 1)
        with pytest.raises(CotError, match=reason):
            parse_cot(bad)

    def test_entities_are_refused(self) -> None:
        bomb = b'<?xml version="1.0"?><!DOCTYPE x [<!ENTITY a "aaaa">]><event/>'
        with pytest.raises(CotError, match="DOCTYPE"):
            parse_cot(bomb)

    @settings(max_examples=fuzz_examples(300), deadline=None)
    @given(st.binary(max_size=2000))
    def test_arbitrary_bytes_raise_only_cot_errors(self, blob: bytes) -> None:
        with contextlib.suppress(CotError):
            parse_cot(blob)


def sink(*destinations: dict[str, Any], **extra: Any) -> CotSink:
    return CotSink("cot", CotSinkConfig.model_validate({"destinations": destinations, **extra}))


def free_udp() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(5)
    return sock


class TestUdp:
    """UDP unicast and multicast, XML and mesh protobuf, received by pytak and a socket."""

    @pytest.mark.anyio
    async def test_pytak_receives_the_events(self) -> None:
        pytak = pytest.importorskip("pytak")
        from urllib.parse import urlparse

        with free_udp() as probe:
            port = probe.getsockname()[1]
        reader, _ = await pytak.create_udp_client(urlparse(f"udp+ro://127.0.0.1:{port}"))
        cot = sink({"uri": f"udp://127.0.0.1:{port}"})
        with anyio.fail_after(10):
            await cot.open()
            await cot.send(EVENTS)
            received = [(await reader.recv())[0] for _ in range(3)]
            await cot.aclose()
        reader.close()
        assert [parse_cot(data).uid for data in received] == [e.uid for e in cot_events()]

    @pytest.mark.anyio
    async def test_mesh_protobuf_over_multicast(self) -> None:
        group = "239.2.3.1"
        receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        receiver.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        receiver.bind(("0.0.0.0", 0))
        port = receiver.getsockname()[1]
        try:
            membership = struct.pack("4s4s", socket.inet_aton(group), socket.inet_aton("127.0.0.1"))
            receiver.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
        except OSError as exc:
            receiver.close()
            pytest.skip(f"no multicast on loopback here: {exc}")
        receiver.settimeout(5)
        cot = sink(
            {"uri": f"udp://{group}:{port}", "protocol": "protobuf", "interface": "127.0.0.1"}
        )
        try:
            with anyio.fail_after(10):
                await cot.open()
                await cot.send([TELEMETRY])
                await cot.aclose()
                data = await anyio.to_thread.run_sync(receiver.recv, 65536)
        except (OSError, TimeoutError) as exc:
            pytest.skip(f"multicast not delivered on this host: {exc}")
        finally:
            receiver.close()
        assert data.startswith(b"\xbf\x01\xbf")
        assert takproto.parse_proto(bytearray(data)).cotEvent.uid == "fischer-F26E-007"


class TakServer:
    """A TAK-server-like peer: optional TLS with client certificates and protocol offer."""

    def __init__(self, *, offer: bool, tls: ssl.SSLContext | None = None) -> None:
        self.offer = offer
        self.tls = tls
        self.received = b""
        self.negotiated = anyio.Event()
        self.port = 0
        self.got_data = anyio.Event()

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        listener = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=0)
        self.port = listener.extra(anyio.abc.SocketAttribute.local_port)
        if self.tls is not None:
            from anyio.streams.tls import TLSListener

            listener = TLSListener(listener, self.tls, standard_compatible=False)  # type: ignore[assignment]
        task_status.started()
        async with listener:
            await listener.serve(self.handle)

    async def handle(self, stream: anyio.abc.ByteStream) -> None:
        async with stream:
            await self.converse(stream)

    async def converse(self, stream: anyio.abc.ByteStream) -> None:
        if self.offer:
            await stream.send(
                b'<?xml version="1.0"?>\n<event version="2.0" uid="protouid" type="t-x-takp-v" '
                b'time="2026-11-22T10:00:00Z" start="2026-11-22T10:00:00Z" '
                b'stale="2026-11-22T10:01:00Z" how="m-g"><point lat="0.0" lon="0.0" '
                b'hae="0.0" ce="999999" le="999999"/><detail><TakControl>'
                b'<TakProtocolSupport version="1"/></TakControl></detail></event>'
            )
        try:
            async for chunk in stream:
                await self.take(stream, chunk)
        except (anyio.BrokenResourceError, ssl.SSLError, OSError):
            return

    async def take(self, stream: anyio.abc.ByteStream, chunk: bytes) -> None:
        self.received += chunk
        if b"t-x-takp-q" in self.received and not self.negotiated.is_set():
            self.negotiated.set()
            self.received = b""
            await stream.send(
                b'<?xml version="1.0"?>\n<event version="2.0" uid="protouid" '
                b'type="t-x-takp-r" time="2026-11-22T10:00:00Z" '
                b'start="2026-11-22T10:00:00Z" stale="2026-11-22T10:01:00Z" how="m-g">'
                b'<point lat="0.0" lon="0.0" hae="0.0" ce="999999" le="999999"/><detail>'
                b'<TakControl><TakResponse status="true"/></TakControl></detail></event>'
            )
        elif self.received:
            self.got_data.set()


def split_stream_frames(data: bytes) -> list[bytes]:
    frames, pos = [], 0
    while pos < len(data):
        assert data[pos] == 0xBF
        pos += 1
        length, shift = 0, 0
        while True:
            byte = data[pos]
            pos += 1
            length |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                break
        frames.append(data[pos : pos + length])
        pos += length
    return frames


class TestStreams:
    """TAK server streaming: XML framing, TLS with client certificates, protobuf negotiation."""

    @pytest.mark.anyio
    async def test_tcp_xml_stream_has_nothing_after_each_event(self) -> None:
        server = TakServer(offer=False)
        with anyio.fail_after(10):
            async with anyio.create_task_group() as tg:
                await tg.start(server.run)
                cot = sink({"uri": f"tcp://127.0.0.1:{server.port}"})
                await cot.open()
                await cot.send(EVENTS)
                expected = b"".join(to_xml(e) for e in cot_events())
                while len(server.received) < len(expected):
                    await server.got_data.wait()
                    server.got_data = anyio.Event()
                await cot.aclose()
                tg.cancel_scope.cancel()
        assert server.received == expected

    def certificates(self, tmp_path: Path) -> tuple[trustme.CA, ssl.SSLContext, dict[str, Any]]:
        ca = trustme.CA()
        server_cert = ca.issue_cert("tak.example.test", "127.0.0.1")
        server = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        server_cert.configure_cert(server)
        ca.configure_trust(server)
        server.verify_mode = ssl.CERT_REQUIRED  # TAK servers demand a client certificate
        client_cert = ca.issue_cert("fischer-gateway")
        ca.cert_pem.write_to_path(str(tmp_path / "ca.pem"))
        client_cert.private_key_and_cert_chain_pem.write_to_path(str(tmp_path / "client.pem"))
        tls = {"ca_file": str(tmp_path / "ca.pem"), "cert_file": str(tmp_path / "client.pem")}
        return ca, server, tls

    @pytest.mark.anyio
    async def test_tls_with_client_certificate_negotiates_protobuf(self, tmp_path: Path) -> None:
        _, server_ctx, tls = self.certificates(tmp_path)
        server = TakServer(offer=True, tls=server_ctx)
        with anyio.fail_after(15):
            async with anyio.create_task_group() as tg:
                await tg.start(server.run)
                cot = sink(
                    {
                        "uri": f"tls://127.0.0.1:{server.port}",
                        "protocol": "negotiate",
                        "tls": {**tls, "server_hostname": "tak.example.test"},
                    }
                )
                await cot.open()
                assert server.negotiated.is_set()
                await cot.send(EVENTS)
                await server.got_data.wait()
                while len(split_stream_frames_safe(server.received)) < 3:
                    server.got_data = anyio.Event()
                    await server.got_data.wait()
                await cot.aclose()
                tg.cancel_scope.cancel()
        uids = [
            takproto.parse_proto(bytearray(stream_frame(frame))).cotEvent.uid
            for frame in split_stream_frames(server.received)
        ]
        assert uids == [e.uid for e in cot_events()]

    @pytest.mark.anyio
    async def test_pkcs12_client_certificate_with_password_file(self, tmp_path: Path) -> None:
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.serialization import pkcs12

        ca, server_ctx, _ = self.certificates(tmp_path)
        leaf = ca.issue_cert("fischer-gateway")
        key = serialization.load_pem_private_key(leaf.private_key_pem.bytes(), None)
        cert = x509.load_pem_x509_certificate(leaf.cert_chain_pems[0].bytes())
        bundle = pkcs12.serialize_key_and_certificates(
            b"gw",
            key,
            cert,
            None,
            serialization.BestAvailableEncryption(b"s3cret"),  # type: ignore[arg-type]
        )
        (tmp_path / "client.p12").write_bytes(bundle)
        (tmp_path / "p12.pass").write_text("s3cret\n")
        server = TakServer(offer=False, tls=server_ctx)
        with anyio.fail_after(15):
            async with anyio.create_task_group() as tg:
                await tg.start(server.run)
                cot = sink(
                    {
                        "uri": f"tls://127.0.0.1:{server.port}",
                        "tls": {
                            "ca_file": str(tmp_path / "ca.pem"),
                            "pkcs12_file": str(tmp_path / "client.p12"),
                            "password_file": str(tmp_path / "p12.pass"),
                        },
                    }
                )
                await cot.open()
                await cot.send([TELEMETRY])
                await server.got_data.wait()
                await cot.aclose()
                tg.cancel_scope.cancel()
        assert parse_cot(server.received).uid == "fischer-F26E-007"

    @pytest.mark.anyio
    async def test_wrong_ca_is_refused_with_a_clear_error(self, tmp_path: Path) -> None:
        _, server_ctx, tls = self.certificates(tmp_path)
        trustme.CA().cert_pem.write_to_path(str(tmp_path / "other-ca.pem"))
        server = TakServer(offer=False, tls=server_ctx)
        with anyio.fail_after(15):
            async with anyio.create_task_group() as tg:
                await tg.start(server.run)
                cot = sink(
                    {
                        "uri": f"tls://127.0.0.1:{server.port}",
                        "tls": {**tls, "ca_file": str(tmp_path / "other-ca.pem")},
                    }
                )
                with pytest.raises(TransientSinkError, match="CERTIFICATE_VERIFY_FAILED"):
                    await cot.open()
                await cot.aclose()
                tg.cancel_scope.cancel()

    @pytest.mark.anyio
    async def test_wrong_hostname_is_refused(self, tmp_path: Path) -> None:
        _, server_ctx, tls = self.certificates(tmp_path)
        server = TakServer(offer=False, tls=server_ctx)
        with anyio.fail_after(15):
            async with anyio.create_task_group() as tg:
                await tg.start(server.run)
                cot = sink(
                    {
                        "uri": f"tls://127.0.0.1:{server.port}",
                        "tls": {**tls, "server_hostname": "evil.example.test"},
                    }
                )
                with pytest.raises(TransientSinkError, match=r"hostname|match"):
                    await cot.open()
                await cot.aclose()
                tg.cancel_scope.cancel()

    @pytest.mark.anyio
    async def test_unreachable_server_is_transient(self) -> None:
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        cot = sink({"uri": f"tcp://127.0.0.1:{port}"})
        with anyio.fail_after(10), pytest.raises(TransientSinkError, match="cannot reach"):
            await cot.open()
        await cot.aclose()


def split_stream_frames_safe(data: bytes) -> list[bytes]:
    try:
        return split_stream_frames(data)
    except (AssertionError, IndexError):
        return []


def test_unchanged_tracks_are_not_resent() -> None:
    cot = sink({"uri": "udp://127.0.0.1:9"})
    event = build(TRACK, cot.options)
    assert event is not None
    assert cot._changed(TRACK, event)
    assert not cot._changed(TRACK, event)
    moved = TRACK.model_copy(update={"position": Position(lat_deg=58.5, lon_deg=15.6)})
    moved_event = build(moved, cot.options)
    assert moved_event is not None
    assert cot._changed(moved, moved_event)


EGM96 = Path("/usr/share/proj/egm96_15.gtx")


@pytest.mark.parametrize(
    ("lat", "lon", "undulation_m"),
    [
        (55.605, 13.0038, 35.5),
        (58.4108, 15.6214, 29.4),
        (59.3293, 18.0686, 23.4),
        (67.8558, 20.2253, 30.0),
    ],
)
def test_egm96_grid_from_proj_data_gives_the_known_undulations(
    lat: float, lon: float, undulation_m: float
) -> None:
    """Debian's proj-data EGM96 grid (installed by .ci/run) against the spec digest's values."""
    if not EGM96.exists():
        pytest.skip("proj-data is not installed")
    value = GeoidGrid(EGM96).undulation(lat, lon)
    assert value == pytest.approx(undulation_m, abs=0.5)
