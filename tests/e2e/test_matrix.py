"""The daemon as operators run it: every shipped sink, the CoT source and the simulator.

One ``fischer-gateway run --config FILE`` subprocess (``python -m gateway``) carries every sink
at once: jsonl, console, memory, null and the CoT sink over UDP unicast (XML), UDP unicast
mesh protobuf, UDP multicast on loopback, TCP, TLS with a client certificate (trustme) and
TCP with TAK protocol v1 negotiation, the GUTE II sink to an HTTPS battery (client
certificate, JSON Schema checked) fed by the fusion and counter_uas processors, the SLB sink
(detections and tracks as JC3IEDM object items over HTTPS), the SWECCIS sink and order source to
one SWECCIS server (TLS, client certificate, XSD checked), the NFFI sink (IP1 TCP and a file,
NFFI 1.3 XSD checked), the Ra 180 sink to a UDP radio gateway with its Swedish voice, the KLV
sink (ST 0601 over UDP, read by stanag4609), plus a UDP and a TCP CoT source, the SLB order
source and the NFFI source (a JAS 39 relay's friendly track over IP1). The simulator
(``fischer-gateway simulate --scenario loitering-munitions``: two airframes, two Lancets seen
on EO and IR) feeds it for more than ten seconds while every peer here decodes
what it receives with takproto and /readyz is sampled; then SIGTERM must stop it cleanly.

The run happens once (module fixture); each test checks one leg of it. Loopback only.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import ssl
import struct
import sys
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import anyio
import anyio.abc
import mgrs
import pytest
import trustme
from anyio.streams.tls import TLSListener
from daemon_support import free_tcp_port, free_udp_port
from geographiclib.geodesic import Geodesic
from gute_peer import GutePeer
from lxml import etree
from slb_peer import SlbPeer
from sweccis_peer import SweccisPeer, order_document

from gateway.events import BlueForce, Position
from sinks.cot.proto import read_varint
from sinks.nffi.codec import NffiOptions, encode_message, parse_message, tracks_of
from sinks.nffi.stream import MessageSplitter
from sinks.ra180.cdm import parse_cdm

takproto = pytest.importorskip("takproto")

RUN_S = 10.5
GROUP = "239.2.3.9"
SLB_ORDER = {
    "order_id": "M-1",
    "issued": "2026-11-22T12:00:00Z",
    "task": "observe_point",
    "location": {"point": {"lat_deg": 65.8235, "lon_deg": 21.6955}},
}


def free_port(kind: int) -> int:
    return free_udp_port() if kind == socket.SOCK_DGRAM else free_tcp_port()


def control(kind: str, detail: str) -> bytes:
    now = datetime.now(UTC)
    stamp = now.strftime("%Y-%m-%dT%H:%M:%S.000Z")
    stale = (now + timedelta(minutes=1)).strftime("%Y-%m-%dT%H:%M:%S.000Z")
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n<event version="2.0" uid="takserver" '
        f'type="t-x-takp-{kind}" how="m-g" time="{stamp}" start="{stamp}" stale="{stale}">'
        '<point lat="0.0" lon="0.0" hae="0.0" ce="9999999.0" le="9999999.0"/>'
        f"<detail><TakControl>{detail}</TakControl></detail></event>"
    ).encode()


def friend(uid: str) -> bytes:
    """A current ATAK position report (stale in five minutes)."""
    now = datetime.now(UTC)
    stamp = now.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
    stale = (now + timedelta(minutes=5)).strftime("%Y-%m-%dT%H:%M:%S.000Z")
    return (
        f'<?xml version="1.0" encoding="UTF-8"?>\n<event version="2.0" uid="{uid}" '
        f'type="a-f-G-U-C" how="m-g" time="{stamp}" start="{stamp}" stale="{stale}">'
        '<point lat="65.82" lon="21.69" hae="9999999.0" ce="9999999.0" le="9999999.0"/>'
        '<detail><contact callsign="3 PLUT"/></detail></event>'
    ).encode()


@dataclass
class StreamPeer:
    """What one TAK-server-like peer received: XML events, then protobuf stream frames."""

    offer: bool = False
    tls: ssl.SSLContext | None = None
    port: int = 0
    xml: list[bytes] = field(default_factory=list)
    proto: bytearray = field(default_factory=bytearray)
    connections: int = 0

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
        buffer, switched = bytearray(), False
        with contextlib.suppress(anyio.BrokenResourceError, ssl.SSLError, OSError):
            async with stream:
                if self.offer:
                    await stream.send(control("v", '<TakProtocolSupport version="1"/>'))
                async for chunk in stream:
                    if switched:
                        self.proto += chunk
                        continue
                    buffer += chunk
                    while (end := buffer.find(b"</event>")) >= 0:
                        event = bytes(buffer[: end + 8])
                        del buffer[: end + 8]
                        if b"t-x-takp-q" in event:
                            await stream.send(control("r", '<TakResponse status="true"/>'))
                            switched = True
                            self.proto += buffer
                            buffer.clear()
                            break
                        self.xml.append(event)

    def frames(self) -> list[Any]:
        """The protobuf stream frames received, decoded by takproto."""
        data, pos, messages = bytes(self.proto), 0, []
        while pos < len(data) and data[pos] == 0xBF:
            length, start = read_varint(data, pos + 1)
            if start + length > len(data):
                break
            messages.append(takproto.parse_proto(bytearray(data[pos : start + length])))
            pos = start + length
        return messages


def udp_receiver(multicast: bool = False) -> socket.socket:
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        if multicast:
            receiver.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            receiver.bind((GROUP, 0))
            membership = struct.pack("4s4s", socket.inet_aton(GROUP), socket.inet_aton("127.0.0.1"))
            receiver.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
        else:
            receiver.bind(("127.0.0.1", 0))
        receiver.setblocking(False)
    except OSError:
        receiver.close()
        raise
    return receiver


async def collect(receiver: socket.socket, into: list[bytes]) -> None:
    while True:
        await anyio.wait_readable(receiver)
        into.append(receiver.recv(65_536))


async def http_get(port: int, path: str) -> tuple[int, bytes]:
    async with await anyio.connect_tcp("127.0.0.1", port) as stream:
        await stream.send(f"GET {path} HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n".encode())
        response = bytearray()
        with contextlib.suppress(anyio.EndOfStream, anyio.BrokenResourceError):
            while True:
                response += await stream.receive()
    head, _, body = bytes(response).partition(b"\r\n\r\n")
    return int(head.split()[1]), body


NFFI_XSD = "nffi/nffi13_sip3/SIP3_Service_ReqRes.xsd_1.xsd"


def nffi_xsd() -> etree.XMLSchema | None:
    """NATO's NFFI 1.3 XSD from the shared corpus (never shipped: its licence), if there."""
    for root in (Path(__file__).resolve().parents[3] / "shared" / "corpus",):
        if (root / NFFI_XSD).is_file():
            return etree.XMLSchema(etree.parse(str(root / NFFI_XSD)))
    return None


@dataclass
class NffiLeg:
    """The NFFI sink's IP1 peer (documents as received), its file, and the source's port."""

    tmp: Path
    source_port: int = 0
    port: int = 0
    documents: list[bytes] = field(default_factory=list)

    async def run(self, *, task_status: anyio.abc.TaskStatus[None]) -> None:
        listener = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=0)
        self.port = listener.extra(anyio.abc.SocketAttribute.local_port)
        task_status.started()
        async with listener:
            await listener.serve(self.handle)

    async def handle(self, stream: anyio.abc.ByteStream) -> None:
        splitter = MessageSplitter(1 << 20)
        with contextlib.suppress(anyio.BrokenResourceError, OSError):
            async with stream:
                async for chunk in stream:
                    self.documents += splitter.feed(chunk)

    def config(self) -> dict[str, list[dict[str, Any]]]:
        """Its sink (own airframes and relayed friends), source and routes."""
        options = {"uri": f"tcp://127.0.0.1:{self.port}", "path": str(self.tmp / "nffi.xml")}
        return {
            "sinks": [{"name": "nffi", "type": "nffi", "options": options | {"country": "SWE"}}],
            "sources": [
                {
                    "name": "nffi_in",
                    "type": "nffi",
                    "uri": f"tcp://127.0.0.1:{self.source_port}",
                    "allow": ["127.0.0.1/32"],
                }
            ],
            "routes": [{"sinks": ["nffi"], "kinds": ["telemetry", "blue_force"]}],
        }

    async def feed(self) -> None:
        """A JAS 39 relay sends one friendly fighter's track to the NFFI source."""
        fighter = BlueForce(
            event_id="-",
            uid="39-7",
            time=datetime.now(UTC),
            callsign="GRIPEN 7",
            position=Position(lat_deg=65.9, lon_deg=21.8, alt_msl_m=4000.0),
            source="-",
            speed_mps=250.0,
            sidc="SFAPMFF--------",
        )
        document = encode_message(tracks_of([fighter], NffiOptions(system="JAS39", country="SWE")))
        async with await anyio.connect_tcp("127.0.0.1", self.source_port) as stream:
            await stream.send(document)

    def file_documents(self) -> list[bytes]:
        return MessageSplitter(1 << 24).feed((self.tmp / "nffi.xml").read_bytes())


@dataclass
class MatrixRun:
    """Everything the run left behind, for the tests to check."""

    tmp: Path
    multicast_error: str | None = None
    datagrams: dict[str, list[bytes]] = field(default_factory=dict)
    peers: dict[str, StreamPeer] = field(default_factory=dict)
    ready_samples: list[int] = field(default_factory=list)
    status: dict[str, Any] = field(default_factory=dict)
    stdout: list[bytes] = field(default_factory=list)
    """What the console sink printed (stdout is for output)."""
    stderr: list[bytes] = field(default_factory=list)
    """The daemon's JSON log lines (logs go to stderr)."""
    returncode: int | None = None
    stop_s: float = 0.0
    gute: GutePeer | None = None
    """The GUTE II battery the gute2 sink posts handoff cues to."""
    slb: SlbPeer | None = None
    """The SLB the slb sink reports to and the slb source takes an order from."""
    sweccis: SweccisPeer | None = None
    """The SWECCIS server of the sweccis sink and order source."""
    nffi: NffiLeg | None = None
    """The NFFI sink's IP1 peer and file, and the NFFI source's port."""


def ra180_sink(run: MatrixRun, ports: dict[str, int]) -> dict[str, Any]:
    """The Ra 180 leg: tracks as CDMs to a UDP radio gateway, new ones spoken to WAV files."""
    return {
        "name": "ra180",
        "type": "ra180",
        "options": {
            "udp": {"host": "127.0.0.1", "port": ports["ra180"]},
            "voice": {"directory": str(run.tmp / "ra180-wav"), "max_files": 10},
        },
    }


def orders_processor() -> dict[str, Any]:
    """The orders leg: a geofence round Gotland, far from the scenario, so every order is
    answered ``rejected`` whatever the simulated airframes report (they fly no missions)."""
    fence = [(57.0, 18.0), (57.0, 19.0), (58.0, 19.0), (58.0, 18.0)]
    corners = [{"lat_deg": lat, "lon_deg": lon} for lat, lon in fence]
    return {"name": "orders", "type": "orders", "options": {"geofence": corners}}


def write_config(run: MatrixRun, ports: dict[str, int], pki: dict[str, str]) -> Path:
    def udp(name: str, uri: str, **extra: Any) -> dict[str, Any]:
        return {"name": name, "type": "cot", "options": {"destinations": [{"uri": uri, **extra}]}}

    cot = [
        udp("cot_udp", f"udp://127.0.0.1:{ports['udp']}"),
        udp("cot_mesh", f"udp://127.0.0.1:{ports['mesh']}", protocol="protobuf"),
        udp("cot_tcp", f"tcp://127.0.0.1:{run.peers['tcp'].port}"),
        udp("cot_tls", f"tls://127.0.0.1:{run.peers['tls'].port}", tls=pki),
        udp("cot_nego", f"tcp://127.0.0.1:{run.peers['nego'].port}", protocol="negotiate"),
    ]
    cot[1]["options"]["takcontrol_interval_s"] = 2
    if run.multicast_error is None:
        cot.append(
            udp("cot_mcast", f"udp+multicast://{GROUP}:{ports['mcast']}?ttl=1&iface=127.0.0.1")
        )
    config = {
        "gateway": {"node_id": "e2e", "shutdown_deadline_s": 3},
        "health": {"host": "127.0.0.1", "port": ports["health"]},
        "airframes": [
            {
                "id": f"F26E-00{n}",
                "sysid": n,
                "links": [{"uri": f"udp://127.0.0.1:{ports['link']}", "security": "unsecured"}],
            }
            for n in (1, 2)
        ],
        "sources": [
            {"name": "mesh_in", "uri": f"udp://127.0.0.1:{ports['source_udp']}"},
            {"name": "stream_in", "uri": f"tcp://127.0.0.1:{ports['source_tcp']}"},
            {"name": "slb_in", "type": "slb", **run.slb.source_options(poll_interval_s=0.5)},
            {"name": "orders_in", "type": "sweccis", **run.sweccis.link_options()},
        ],
        # The scenario's two Lancets (EO 0.80 + IR 0.75) are fused and cued to its battery.
        "processors": [
            {"name": "fusion", "type": "fusion", "options": {"max_speed_mps": 300}},
            {
                "name": "cuas",
                "type": "counter_uas",
                "options": {
                    "batteries": [
                        {
                            "id": "GUTE-E2E",
                            "lat_deg": 65.8235,
                            "lon_deg": 21.6955,
                            "effectors": ["TRACKFIRE_30MM", "TRIDON_MK2_40MM"],
                        }
                    ],
                },
            },
            orders_processor(),
        ],
        "sinks": [
            ra180_sink(run, ports),
            {"name": "archive", "type": "jsonl", "options": {"path": str(run.tmp / "a.jsonl")}},
            {"name": "console", "type": "console", "options": {"format": "json"}},
            {"name": "mem", "type": "memory"},
            {"name": "null", "type": "null"},
            {"name": "gute", "type": "gute2", "options": run.gute.sink_options()},
            {"name": "slb", "type": "slb", "options": run.slb.sink_options()},
            {"name": "sweccis", "type": "sweccis", "options": run.sweccis.link_options()},
            *cot,
            klv_sink(ports),
        ],
        "routes": [
            klv_route(),
            {"sinks": ["archive", "mem", "null"]},
            {"sinks": ["console"], "kinds": ["telemetry"], "max_rate_hz": 1},
            {"sinks": [c["name"] for c in cot], "kinds": ["telemetry", "detection"]},
            {"sinks": ["gute"], "kinds": ["handoff"]},
            {"sinks": ["slb"], "kinds": ["detection", "track"]},
            {"sinks": ["sweccis"], "kinds": ["telemetry", "detection", "track"]},
            {"sinks": ["ra180"], "kinds": ["track"]},
        ],
    }
    if run.nffi is not None:
        for key, items in run.nffi.config().items():
            config[key] += items
    path = run.tmp / "config.yaml"
    path.write_text(json.dumps(config, indent=1))  # JSON is YAML
    return path


def klv_sink(ports: dict[str, int]) -> dict[str, Any]:
    """The KLV leg: ST 0601 packets over UDP to the ``klv`` receiver."""
    udp = {"host": "127.0.0.1", "port": ports["klv"]}
    return {"name": "klv", "type": "klv", "options": {"udp": udp, "mission_id": "E2E"}}


def klv_route() -> dict[str, Any]:
    return {"sinks": ["klv"], "kinds": ["video_frame_metadata"]}


async def drain(stream: anyio.abc.ByteReceiveStream, into: list[bytes]) -> None:
    buffer = b""
    with contextlib.suppress(anyio.EndOfStream, anyio.BrokenResourceError):
        async for chunk in stream:
            buffer += chunk
            *lines, buffer = buffer.split(b"\n")
            into.extend(lines)


async def feed_sources(ports: dict[str, int]) -> None:
    """ATAK peers: a mesh protobuf report over UDP, an XML report over TCP."""
    mesh = bytes(takproto.xml2proto(friend("ANDROID-MESH"), takproto.TAKProtoVer.MESH))
    async with await anyio.create_connected_udp_socket(
        remote_host="127.0.0.1", remote_port=ports["source_udp"]
    ) as sock:
        await sock.send(mesh)
    async with await anyio.connect_tcp("127.0.0.1", ports["source_tcp"]) as stream:
        await stream.send(b'<detail><contact callsign="X"/></detail>' + friend("ANDROID-TCP"))


@contextlib.asynccontextmanager
async def daemon(config: Path, run: MatrixRun) -> AsyncIterator[anyio.abc.Process]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    command = [sys.executable, "-m", "gateway", "run", "--config", str(config)]
    async with await anyio.open_process(command, env=env) as process:
        try:
            yield process
        finally:
            if process.returncode is None:
                process.kill()


async def scenario(run: MatrixRun, pki_files: dict[str, str], server_tls: ssl.SSLContext) -> None:
    run.peers = {"tcp": StreamPeer(), "tls": StreamPeer(tls=server_tls), "nego": StreamPeer(True)}
    ports = {"health": free_port(socket.SOCK_STREAM), "link": free_port(socket.SOCK_DGRAM)}
    ports |= {
        "source_udp": free_port(socket.SOCK_DGRAM),
        "source_tcp": free_port(socket.SOCK_STREAM),
    }
    with contextlib.ExitStack() as sockets:
        names = ("udp", "mesh", "ra180", "klv")
        receivers = {name: sockets.enter_context(udp_receiver()) for name in names}
        try:
            receivers["mcast"] = sockets.enter_context(udp_receiver(multicast=True))
        except OSError as exc:
            run.multicast_error = f"this host cannot join {GROUP} on loopback: {exc}"
        for name, receiver in receivers.items():
            ports[name] = receiver.getsockname()[1]
            run.datagrams[name] = []
        async with (
            anyio.create_task_group() as tg,
            GutePeer(run.tmp / "gute") as gute,
            SlbPeer(run.tmp / "slb") as slb,
            SweccisPeer(run.tmp / "sweccis") as sweccis,
        ):
            run.gute, run.slb, run.sweccis = gute, slb, sweccis
            run.nffi = NffiLeg(run.tmp, source_port=free_port(socket.SOCK_STREAM))
            await tg.start(run.nffi.run)
            slb.queue_order(SLB_ORDER)
            await sweccis.push_order(order_document("m-doc-1", "M-1"))  # sent on registering
            for peer in run.peers.values():
                await tg.start(peer.run)
            for name, receiver in receivers.items():
                tg.start_soon(collect, receiver, run.datagrams[name])
            config = write_config(run, ports, pki_files)
            async with daemon(config, run) as process:
                assert process.stdout is not None
                assert process.stderr is not None
                tg.start_soon(drain, process.stdout, run.stdout)
                tg.start_soon(drain, process.stderr, run.stderr)
                with anyio.fail_after(20):
                    while True:  # ready: every link bound, every sink open
                        if process.returncode is not None:
                            await anyio.sleep(0.1)  # let ``drain`` take the last lines
                            tail = b"\n".join(run.stderr[-20:]).decode(errors="replace")
                            pytest.fail(f"the daemon exited {process.returncode}:\n{tail}")
                        with contextlib.suppress(OSError):
                            if (await http_get(ports["health"], "/readyz"))[0] == 200:
                                break
                        await anyio.sleep(0.05)
                target = f"udp://127.0.0.1:{ports['link']}"
                simulate = [
                    sys.executable, "-m", "gateway", "simulate", "--scenario",
                    "loitering-munitions", "--to", target, "--duration", str(RUN_S * 3),
                    "--speed", "3",
                ]  # fmt: skip
                async with await anyio.open_process(simulate) as simulator:
                    await feed_sources(ports)
                    await run.nffi.feed()
                    with anyio.fail_after(RUN_S + 10):
                        while simulator.returncode is None:
                            run.ready_samples.append(
                                (await http_get(ports["health"], "/readyz"))[0]
                            )
                            with anyio.move_on_after(0.5):
                                await simulator.wait()
                    assert simulator.returncode == 0
                run.status = json.loads((await http_get(ports["health"], "/status"))[1])
                started = anyio.current_time()
                process.send_signal(signal.SIGTERM)
                with anyio.fail_after(10):
                    run.returncode = await process.wait()
                run.stop_s = anyio.current_time() - started
            tg.cancel_scope.cancel()


@pytest.fixture(scope="module")
def matrix(tmp_path_factory: pytest.TempPathFactory) -> MatrixRun:
    """Run the whole matrix once (about 13 s) and keep what every peer received."""
    tmp = tmp_path_factory.mktemp("matrix")
    ca = trustme.CA()
    server = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ca.issue_cert("127.0.0.1").configure_cert(server)
    ca.configure_trust(server)
    server.verify_mode = ssl.CERT_REQUIRED  # TAK servers demand a client certificate
    ca.cert_pem.write_to_path(str(tmp / "ca.pem"))
    ca.issue_cert("fischer-gateway").private_key_and_cert_chain_pem.write_to_path(
        str(tmp / "client.pem")
    )
    run = MatrixRun(tmp)
    pki = {"ca_file": str(tmp / "ca.pem"), "cert_file": str(tmp / "client.pem")}
    anyio.run(scenario, run, pki, server, backend="asyncio")
    return run


def logs(run: MatrixRun) -> list[dict[str, Any]]:
    lines = [json.loads(line) for line in run.stderr if line.startswith(b"{")]
    return [line for line in lines if "level" in line]


def sink_status(run: MatrixRun, name: str) -> dict[str, Any]:
    (status,) = [s for s in run.status["sinks"] if s["sink"] == name]
    return status  # type: ignore[no-any-return]


def our_uids(messages: list[Any]) -> set[str]:
    return {m.cotEvent.uid for m in messages if m.HasField("cotEvent")}


class TestDaemon:
    """The daemon stays ready for the whole run and stops cleanly on SIGTERM."""

    def test_ready_throughout_and_a_clean_exit(self, matrix: MatrixRun) -> None:
        assert len(matrix.ready_samples) >= 18  # sampled every 0.5 s for RUN_S
        assert set(matrix.ready_samples) == {200}
        assert matrix.returncode == 0
        assert matrix.stop_s < 3 + 2  # the shutdown deadline, plus interpreter exit
        events = [line["event"] for line in logs(matrix)]
        assert events[-1] == "gateway_stopped"
        failures = [e for e in logs(matrix) if e["level"] in ("error", "critical")]
        assert failures == []

    def test_every_sink_opened_and_delivered(self, matrix: MatrixRun) -> None:
        names = ["archive", "console", "mem", "null", "cot_udp", "cot_mesh", "cot_tcp"]
        names += ["cot_tls", "cot_nego", "slb"]
        names += [] if matrix.multicast_error else ["cot_mcast"]
        for name in names:
            status = sink_status(matrix, name)
            assert (status["state"], status["open"]) == ("open", True), status
            assert status["sent"] > 0, status
            assert status["dead_letters"] == 0, status


class TestPlainSinks:
    """jsonl, console: what the operator reads."""

    def test_jsonl_archive_has_telemetry_detections_and_blue_force(self, matrix: MatrixRun) -> None:
        lines = [json.loads(line) for line in (matrix.tmp / "a.jsonl").read_text().splitlines()]
        kinds = {line["kind"] for line in lines}
        assert {"telemetry", "detection", "blue_force", "link_state"} <= kinds
        assert {line["airframe"] for line in lines if line["kind"] == "telemetry"} == {
            "F26E-001",
            "F26E-002",
        }

    def test_console_prints_json_events(self, matrix: MatrixRun) -> None:
        lines = [json.loads(line) for line in matrix.stdout if line.startswith(b"{")]
        printed = [line for line in lines if line.get("kind") == "telemetry"]
        assert len(printed) >= 2 * 8  # two airframes at most once a second for RUN_S


class TestCotUdp:
    """CoT to UDP peers: XML unicast, mesh protobuf unicast, multicast on loopback."""

    def test_unicast_xml(self, matrix: MatrixRun) -> None:
        messages = [takproto.parse_proto(bytearray(d)) for d in matrix.datagrams["udp"]]
        assert {"fischer-F26E-001", "fischer-F26E-002"} <= our_uids(messages)
        assert all(d.startswith(b"<?xml") for d in matrix.datagrams["udp"])

    def test_unicast_mesh_protobuf_with_takcontrol(self, matrix: MatrixRun) -> None:
        data = matrix.datagrams["mesh"]
        assert all(d.startswith(b"\xbf\x01\xbf") for d in data)
        messages = [takproto.parse_proto(bytearray(d)) for d in data]
        assert {"fischer-F26E-001", "fischer-F26E-002"} <= our_uids(messages)
        announced = [m for m in messages if m.HasField("takControl")]
        assert len(announced) >= 4  # every 2 s for RUN_S
        assert {m.takControl.maxProtoVersion for m in announced} == {1}

    def test_multicast_on_loopback(self, matrix: MatrixRun) -> None:
        if matrix.multicast_error:
            pytest.skip(matrix.multicast_error)
        messages = [takproto.parse_proto(bytearray(d)) for d in matrix.datagrams["mcast"]]
        assert {"fischer-F26E-001", "fischer-F26E-002"} <= our_uids(messages)


class TestCotStreams:
    """CoT to TAK-server-like peers: TCP XML, TLS with a client certificate, negotiation."""

    def test_tcp_xml(self, matrix: MatrixRun) -> None:
        peer = matrix.peers["tcp"]
        messages = [takproto.parse_proto(bytearray(e.strip())) for e in peer.xml]
        assert {"fischer-F26E-001", "fischer-F26E-002"} <= our_uids(messages)
        assert peer.connections == 1

    def test_tls_with_client_certificate(self, matrix: MatrixRun) -> None:
        peer = matrix.peers["tls"]
        messages = [takproto.parse_proto(bytearray(e.strip())) for e in peer.xml]
        assert {"fischer-F26E-001", "fischer-F26E-002"} <= our_uids(messages)
        assert peer.connections == 1

    def test_negotiated_protobuf(self, matrix: MatrixRun) -> None:
        peer = matrix.peers["nego"]
        assert peer.xml == []  # nothing but the request before the switch
        assert {"fischer-F26E-001", "fischer-F26E-002"} <= our_uids(peer.frames())


class TestCotSource:
    """ATAK positions in: mesh protobuf over UDP, XML over TCP after a stray fragment."""

    def test_both_sources_took_their_report(self, matrix: MatrixRun) -> None:
        counts = {s["source"]: s["counts"] for s in matrix.status["sources"]}
        assert counts["mesh_in"] == {"accepted": 1}
        assert counts["stream_in"] == {"fragment": 1, "accepted": 1}
        lines = [json.loads(line) for line in (matrix.tmp / "a.jsonl").read_text().splitlines()]
        uids = {line["uid"] for line in lines if line["kind"] == "blue_force"}
        assert uids - {"SWE.JAS39.39-7"} == {"ANDROID-MESH", "ANDROID-TCP"}  # that one is NFFI's


class TestCounterUas:
    """Detections fused into tracks, cued to a GUTE II battery over HTTPS with client certs."""

    def test_the_battery_got_each_cue_once_and_valid(self, matrix: MatrixRun) -> None:
        gute = matrix.gute
        assert gute is not None
        assert gute.accepted, f"no handoff reached the battery: {matrix.status['processors']}"
        assert [r.status for r in gute.posts] == [201] * len(gute.accepted)
        by_track: dict[str, set[str]] = {}
        for document in gute.accepted.values():
            assert document["operator_authorisation_required"] is True
            assert document["battery"]["id"] == "GUTE-E2E"
            assert document["track"]["object_class"] == "loitering_munition"
            assert document["track"]["confidence"] >= 0.95 - 1e-9
            by_track.setdefault(document["track"]["track_id"], set()).add(document["handoff_id"])
        assert all(len(ids) == 1 for ids in by_track.values())

    def test_the_tracks_and_cues_are_archived_and_processors_report(
        self, matrix: MatrixRun
    ) -> None:
        lines = [json.loads(line) for line in (matrix.tmp / "a.jsonl").read_text().splitlines()]
        kinds = {line["kind"] for line in lines}
        assert {"track", "handoff"} <= kinds
        processors = {p["processor"]: p for p in matrix.status["processors"]}
        assert processors["fusion"]["state"] == "running"
        detail = processors["cuas"]["detail"]
        assert matrix.gute is not None
        assert detail["handed_off"] + detail["revised"] == len(matrix.gute.accepted)


class TestSlb:
    """Detections and fused tracks as JC3IEDM object items to SLB; an order back from it."""

    def test_slb_got_each_detection_and_track_once(self, matrix: MatrixRun) -> None:
        slb = matrix.slb
        assert slb is not None
        lines = [json.loads(line) for line in (matrix.tmp / "a.jsonl").read_text().splitlines()]
        reported = {e["event_id"] for e in lines if e["kind"] in ("detection", "track")}
        assert reported
        # Sent before SIGTERM, or drained at shutdown: every one, once, schema-valid.
        assert set(slb.accepted) == reported
        assert {r.status for r in slb.posts if "/object-items" in r.path} == {201}
        classes = {d["fischer"]["object_class"] for d in slb.accepted.values()}
        assert classes == {"loitering_munition"}

    def test_the_order_arrived_and_was_acknowledged(self, matrix: MatrixRun) -> None:
        slb = matrix.slb
        assert slb is not None
        lines = [json.loads(line) for line in (matrix.tmp / "a.jsonl").read_text().splitlines()]
        orders = [e for e in lines if e["kind"] == "order" and e["source"] == "slb_in"]
        assert [o["event_id"] for o in orders] == ["slb-order-M-1"]
        assert slb.receipts_for("M-1")[0]["status"] == "received"

    def test_the_orders_processor_answered_the_order_at_slb(self, matrix: MatrixRun) -> None:
        slb = matrix.slb
        assert slb is not None
        receipts = slb.receipts_for("M-1")
        # Polled before the simulator's airframes were heard, the order waits for them.
        assert [r["status"] for r in receipts if r["status"] != "waiting"] == [
            "received",
            "rejected",
        ]
        assert receipts[-1]["reason"].startswith("geofence: ")
        assert receipts[-1]["event_id"] == "slb-order-M-1-rejected"


class TestSweccis:
    """SWECCIS both ways: XSD-valid FAS documents out, an order in, acknowledged once held."""

    def test_the_server_got_valid_documents_of_each_fas(self, matrix: MatrixRun) -> None:
        peer = matrix.sweccis
        assert peer is not None
        assert peer.invalid == []
        assert {"Intel", "Logistics", "Operations"} <= {r.root for r in peer.documents}
        assert all(r.status == "accepted" for r in peer.documents if r.root == "Intel")
        status = sink_status(matrix, "sweccis")
        assert (status["state"], status["dead_letters"]) == ("open", 0)

    def test_the_order_was_archived_and_acknowledged(self, matrix: MatrixRun) -> None:
        peer = matrix.sweccis
        assert peer is not None
        assert peer.order_acks == [("m-doc-1", "accepted", None)]
        lines = [json.loads(line) for line in (matrix.tmp / "a.jsonl").read_text().splitlines()]
        orders = [e for e in lines if e["kind"] == "order" and e["source"] == "orders_in"]
        assert [o["event_id"] for o in orders] == ["sweccis-order-M-1"]
        counts = {s["source"]: s["counts"] for s in matrix.status["sources"]}
        assert counts["orders_in"]["accepted"] == 1
        assert {k for k in counts["orders_in"] if not k.startswith("status_")} == {"accepted"}

    def test_the_orders_processor_answered_the_order_at_sweccis(self, matrix: MatrixRun) -> None:
        peer = matrix.sweccis
        assert peer is not None
        assert [s for s in peer.order_statuses("M-1") if s != "waiting"] == ["rejected"]


class TestNffi:
    """NFFI 1.3 both ways: own airframes and relayed friends out over IP1 and to a file (XSD
    checked); a JAS 39 relay's track in through the NFFI source as blue force."""

    def test_the_ip1_peer_and_the_file_got_valid_tracks(self, matrix: MatrixRun) -> None:
        leg = matrix.nffi
        assert leg is not None
        status = sink_status(matrix, "nffi")
        assert (status["state"], status["open"], status["dead_letters"]) == ("open", True, 0)
        tracks = [t for d in leg.documents for t in parse_message(d).tracks]
        units = {t.transponder_id for t in tracks}
        # Own airframes, and the friends relayed from ATAK and from the JAS 39 relay.
        assert {"F26E-001", "F26E-002", "ANDROID-MESH", "ANDROID-TCP"} <= units
        assert "SWE.JAS39.39-7" in units
        assert {d.strip() for d in leg.documents} <= {d.strip() for d in leg.file_documents()}
        xsd = nffi_xsd()
        if xsd is None:
            pytest.skip(f"the NFFI 1.3 XSD ({NFFI_XSD}) is not in shared/corpus")
        for document in leg.documents + leg.file_documents():
            assert xsd.validate(etree.fromstring(document)), str(xsd.error_log)

    def test_the_relayed_fighter_came_in_as_blue_force(self, matrix: MatrixRun) -> None:
        counts = {s["source"]: s["counts"] for s in matrix.status["sources"]}
        assert counts["nffi_in"] == {"accepted": 1}
        lines = [json.loads(line) for line in (matrix.tmp / "a.jsonl").read_text().splitlines()]
        (fighter,) = [e for e in lines if e["kind"] == "blue_force" and e["source"] == "nffi"]
        assert (fighter["uid"], fighter["sidc"]) == ("SWE.JAS39.39-7", "SFAPMFF--------")
        assert fighter["speed_mps"] == pytest.approx(250.0)


class TestRa180:
    """Fused hostile tracks to the Ra 180 net: CDMs where the tracks are, and Swedish voice."""

    def test_the_radio_gateway_heard_each_new_munition_where_it_was(
        self, matrix: MatrixRun
    ) -> None:
        cdms = [parse_cdm(d.decode("ascii")) for d in matrix.datagrams["ra180"]]
        assert cdms, f"nothing reached the radio gateway: {sink_status(matrix, 'ra180')}"
        assert {(c.hostility, c.class_abbreviation) for c in cdms} == {("FIENDE", "LUFT-MUN")}
        new = [c for c in cdms if c.type == "MAL"]
        assert len({c.number for c in new}) == len(new) >= 1  # each target announced once
        lines = [json.loads(line) for line in (matrix.tmp / "a.jsonl").read_text().splitlines()]
        tracks = [e for e in lines if e["kind"] == "track" and e["hostility"] == "hostile"]
        for cdm in cdms:  # each grid reference is one of the fused positions, to its 10 m cell
            lat, lon = mgrs.MGRS().toLatLon(cdm.mgrs.replace(" ", ""))
            nearest = min(
                Geodesic.WGS84.Inverse(
                    lat, lon, t["position"]["lat_deg"], t["position"]["lon_deg"]
                )["s12"]
                for t in tracks
            )
            assert nearest < 7.1 + 0.1
        detail = sink_status(matrix, "ra180")["detail"]
        # A datagram counts as sent once no refusal came back within 0.2 s
        # (gateway.transports.udp_peer): the last one may be in that window at the snapshot.
        assert detail["sent"] <= len(cdms) <= detail["sent"] + 1
        assert detail["radio_state"] == "sending"

    def test_new_targets_were_spoken_to_wav_files(self, matrix: MatrixRun) -> None:
        voice = sink_status(matrix, "ra180")["detail"]["voice"]
        if shutil.which("espeak-ng") is None:
            assert voice["state"] == "unavailable", voice
            pytest.skip("espeak-ng is not installed (Debian package espeak-ng)")
        assert voice["rendered"] >= 1, voice
        assert list((matrix.tmp / "ra180-wav").glob("*-MAL.wav"))


class TestKlv:
    """STANAG 4609 metadata: the camera of F26E-001 as ST 0601 KLV over UDP."""

    def test_packets_decode_alike_in_ours_and_stanag4609(self, matrix: MatrixRun) -> None:
        from sinks.klv.st0601 import decode

        stanag = pytest.importorskip("stanag4609.st0601")
        packets = matrix.datagrams["klv"]
        assert len(packets) >= 5 * RUN_S  # 5 Hz camera reports for the whole run, and more
        for packet in packets:
            ours = decode(packet)  # checksum verified
            theirs = {f.definition.tag: f.value for f in stanag.decode_uas_local_set(packet).fields}
            assert theirs[13] == pytest.approx(ours[13], abs=1e-7)
            assert (ours[3], ours[4], ours[10], ours[65]) == ("E2E", "F26E-001", "Fischer 26E", 19)
            # The simulated gimbal holds the orbit's centre in view (loitering-munitions.yaml).
            assert ours[23] == pytest.approx(65.8600, abs=1e-6)
            assert ours[24] == pytest.approx(21.6400, abs=1e-6)
            assert ours[21] == pytest.approx((700**2 + 450**2) ** 0.5, rel=0.01)
        status = sink_status(matrix, "klv")
        assert (status["state"], status["dead_letters"]) == ("open", 0)
