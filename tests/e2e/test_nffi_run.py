"""NFFI both ways in the daemon as operators run it (``fischer-gateway run --config FILE``).

Out: the simulator's two airframes (``fischer-gateway simulate``) become NFFI 1.3 tracks sent
over IP1 (TCP) to a test peer and appended to a file; every document either way must
validate against the NFFI 1.3 XSD (lxml; the XSD is read from shared/corpus, skipped when
absent). In: a test peer plays a JAS 39 relay, connects to the NFFI source over TCP and sends
a friendly fighter's track; it must come out of the CoT sink to a UDP peer as a friendly air
position (decoded by takproto), with its speed converted from km/h to m/s.
"""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from daemon_support import free_tcp_port, free_udp_port, running, wait_until
from lxml import etree

from gateway.events import BlueForce, Position
from sinks.nffi.codec import NffiOptions, encode_message, parse_message, tracks_of
from sinks.nffi.stream import MessageSplitter

takproto = pytest.importorskip("takproto")
pytestmark = pytest.mark.timeout(120)

XSD_NAME = "nffi/nffi13_sip3/SIP3_Service_ReqRes.xsd_1.xsd"


def nffi_xsd() -> etree.XMLSchema | None:
    for root in (Path(__file__).resolve().parents[2] / ".." / "shared" / "corpus",):
        if (root / XSD_NAME).is_file():
            return etree.XMLSchema(etree.parse(str(root / XSD_NAME)))
    return None


def jas39_report(at: datetime) -> bytes:
    """A JAS 39 relay's NFFI document: one friendly fighter at 900 km/h."""
    fighter = BlueForce(
        event_id="-",
        uid="39-7",
        time=at,
        callsign="GRIPEN 7",
        position=Position(lat_deg=65.9, lon_deg=21.8, alt_msl_m=4000.0),
        source="-",
        speed_mps=250.0,
        course_deg=80.0,
        sidc="SFAPMFF--------",
    )
    return encode_message(tracks_of([fighter], NffiOptions(system="JAS39-RELAY", country="SWE")))


@dataclass
class Ip1Peer:
    """A ground C2 system's IP1 receiver: one TCP listener, documents split as they arrive."""

    sock: socket.socket
    documents: list[bytes] = field(default_factory=list)
    connections: int = 0

    @property
    def port(self) -> int:
        return int(self.sock.getsockname()[1])

    def serve(self) -> None:
        with contextlib.suppress(OSError):
            while True:
                conn, _ = self.sock.accept()
                self.connections += 1
                splitter = MessageSplitter(1 << 20)
                with conn:
                    while chunk := conn.recv(65_536):
                        self.documents += splitter.feed(chunk)


@contextlib.contextmanager
def ip1_peer() -> Iterator[Ip1Peer]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.listen(4)
    peer = Ip1Peer(sock)
    thread = threading.Thread(target=peer.serve, daemon=True)
    thread.start()
    try:
        yield peer
    finally:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        sock.close()
        thread.join(timeout=5)


def write_config(tmp: Path, link: int, source_port: int, peer: Ip1Peer, cot: int) -> Path:
    config = {
        "gateway": {"node_id": "nffi-e2e", "shutdown_deadline_s": 3},
        "health": {"host": "127.0.0.1", "port": 0},
        "airframes": [
            {
                "id": f"F26E-00{n}",
                "sysid": n,
                "links": [{"uri": f"udp://127.0.0.1:{link}", "security": "unsecured"}],
            }
            for n in (1, 2)
        ],
        "sources": [
            {
                "name": "jas_relay",
                "type": "nffi",
                "uri": f"tcp://127.0.0.1:{source_port}",
                "allow": ["127.0.0.0/8"],
            }
        ],
        "sinks": [
            {
                "name": "nffi_c2",
                "type": "nffi",
                "options": {
                    "uri": f"tcp://127.0.0.1:{peer.port}",
                    "path": str(tmp / "nffi.xml"),
                    "country": "SWE",
                    "sec_policy_name": "NATO",
                    "sec_classification": "UNCLASSIFIED",
                },
            },
            {
                "name": "atak",
                "type": "cot",
                "options": {
                    "destinations": [f"udp://127.0.0.1:{cot}"],
                    "kinds": ["telemetry", "blue_force"],
                },
            },
            {"name": "archive", "type": "jsonl", "options": {"path": str(tmp / "a.jsonl")}},
        ],
        "routes": [
            {"sinks": ["nffi_c2"], "kinds": ["telemetry"], "max_rate_hz": 1},
            {"sinks": ["atak"], "kinds": ["blue_force"]},
            {"sinks": ["archive"]},
        ],
    }
    path = tmp / "node.yaml"
    path.write_text(json.dumps(config, indent=1))  # JSON is YAML
    return path


@dataclass
class NffiRun:
    peer_documents: list[bytes]
    file_documents: list[bytes]
    cot: list[Any]
    status: dict[str, Any]


@pytest.fixture(scope="module")
def nffi_run(tmp_path_factory: pytest.TempPathFactory) -> NffiRun:
    tmp = tmp_path_factory.mktemp("nffi")
    link, source_port = free_udp_port(), free_tcp_port()
    cot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    cot.bind(("127.0.0.1", 0))
    cot.settimeout(0.2)
    datagrams: list[bytes] = []
    with cot, ip1_peer() as peer:
        config = write_config(tmp, link, source_port, peer, cot.getsockname()[1])
        with running(config) as daemon:
            command = [sys.executable, "-m", "gateway", "simulate", "--airframes", "2"]
            command += ["--to", f"udp://127.0.0.1:{link}", "--duration", "5"]
            simulator = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            try:
                with socket.create_connection(("127.0.0.1", source_port), timeout=10) as relay:
                    relay.sendall(jas39_report(datetime.now(UTC) - timedelta(seconds=2)))

                    def fighter_seen() -> bool:
                        with contextlib.suppress(TimeoutError):
                            datagrams.append(cot.recv(65_536))
                        return any(b"SWE.JAS39-RELAY.39-7" in d for d in datagrams)

                    wait_until(fighter_seen, 20.0, "the relayed fighter on the CoT peer")
                _, errors = simulator.communicate(timeout=60)
                assert simulator.returncode == 0, errors.decode(errors="replace")
            finally:
                if simulator.poll() is None:
                    simulator.kill()
                    simulator.wait()

            def both_airframes_out() -> bool:
                tracks = [t for d in list(peer.documents) for t in parse_message(d).tracks]
                return {t.transponder_id for t in tracks} == {"F26E-001", "F26E-002"}

            wait_until(both_airframes_out, 15.0, "both airframes' NFFI tracks at the IP1 peer")
            status = daemon.status()
        file_documents = MessageSplitter(1 << 22).feed((tmp / "nffi.xml").read_bytes())
        return NffiRun(
            list(peer.documents),
            file_documents,
            [takproto.parse_proto(bytearray(d)) for d in datagrams],
            status,
        )


def test_own_airframes_go_out_as_nffi_over_ip1_and_to_a_file(nffi_run: NffiRun) -> None:
    xsd = nffi_xsd()
    if xsd is None:
        pytest.skip(f"the NFFI 1.3 XSD ({XSD_NAME}) is not in shared/corpus")
    assert nffi_run.peer_documents
    assert nffi_run.file_documents
    for document in nffi_run.peer_documents + nffi_run.file_documents:
        assert xsd.validate(etree.fromstring(document)), str(xsd.error_log)
    tracks = [t for d in nffi_run.peer_documents for t in parse_message(d).tracks]
    assert {t.transponder_id for t in tracks} == {"F26E-001", "F26E-002"}
    assert {(t.country, t.system) for t in tracks} == {("SWE", "FISCHER-GW")}
    assert all(t.unit_symbol == "SFAPMFQ--------" for t in tracks)
    in_file = {d.strip() for d in nffi_run.file_documents}
    assert {d.strip() for d in nffi_run.peer_documents} <= in_file


def test_a_relayed_nffi_friend_comes_out_as_cot_blue_force(nffi_run: NffiRun) -> None:
    (fighter,) = {
        m.cotEvent.uid: m.cotEvent
        for m in nffi_run.cot
        if m.HasField("cotEvent") and m.cotEvent.uid == "SWE.JAS39-RELAY.39-7"
    }.values()
    assert fighter.type == "a-f-A-M-F-F"  # friendly fighter, from the NFFI unit symbol
    assert (fighter.lat, fighter.lon) == (65.9, 21.8)
    assert fighter.detail.contact.callsign == "GRIPEN-7"
    assert fighter.detail.track.speed == pytest.approx(250.0)  # 900 km/h on the wire
    assert fighter.detail.track.course == pytest.approx(80.0)
    counts = {s["source"]: s["counts"] for s in nffi_run.status["sources"]}
    assert counts["jas_relay"] == {"accepted": 1}
    (sink,) = [s for s in nffi_run.status["sinks"] if s["sink"] == "nffi_c2"]
    assert (sink["state"], sink["dead_letters"]) == ("open", 0)
