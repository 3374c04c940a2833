"""Durable delivery to brigade C2 through outages, as operators run the gateway.

``fischer-gateway run --config FILE`` in a child process with a spool file and an ``slb`` sink
to a real HTTPS SLB (``SlbPeer``: client certificate required, every body checked against the
shipped schema, duplicates by ``Idempotency-Key`` answered 409 and never recorded twice).
``fischer-gateway simulate`` plays one airframe watching a tank at 5 Hz, re-sending every
detection until the gateway acknowledges it.

1. SLB down for 60 s while detections flow, and inside that outage the airframe's link cut
   for 30 s (``UdpCut`` drops both directions): SLB ends with every detection the airframe
   sent, each once, in the order the gateway accepted them.
2. SLB down, the gateway killed with SIGKILL mid-stream and started again 5 s later on the
   same spool: everything the first gateway had acknowledged (so the airframe forgot it) is
   still delivered, every detection reaches SLB exactly once after de-duplication.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Daemon, archive_events, free_udp_port, running, wait_until
from slb_peer import SlbPeer
from udp_cut import UdpCut

pytestmark = pytest.mark.timeout(200)

GATEWAY = [sys.executable, "-m", "gateway"]
SUMMARY = re.compile(
    r"\(sysid 1\): detections sent (?P<sent>\d+), re-sent (?P<resent>\d+), acknowledged "
    r"(?P<acknowledged>\d+), dropped (?P<dropped>\d+), unacknowledged (?P<unacknowledged>\d+)"
    r".*; sends refused (?P<refused>\d+)"
)
DETECTION_ID = re.compile(r"^F26E-001-det-(\d+)-\d+$")
SCENARIO = """\
name: watch
duration_s: {duration}
seed: 7
airframes:
  - id: F26E-001
    sysid: 1
    orbit: {{centre_lat_deg: 65.84, centre_lon_deg: 21.70, radius_m: 500, alt_msl_m: 600,
            speed_mps: 25}}
    sensors:
      - {{sensor: eo, range_m: 8000, confidence: 0.8, sigma_h_m: 10, rate_hz: 5}}
targets:
  - id: T-1
    class: tank
    subtype: T-72B3
    speed_mps: 2
    path:
      - {{lat_deg: 65.85, lon_deg: 21.70, alt_msl_m: 60}}
      - {{lat_deg: 65.86, lon_deg: 21.71, alt_msl_m: 60}}
"""


def write_node(tmp_path: Path, peer: SlbPeer, link: int) -> tuple[Path, Path]:
    tls = peer.tls_options()
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
spool: {{path: '{tmp_path / "spool.db"}'}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: radio}}]}}
sinks:
  - name: slb
    type: slb
    options: {{base_url: '{peer.base_url}', ca_file: '{tls["ca_file"]}',
               cert_file: '{tls["cert_file"]}', key_file: '{tls["key_file"]}',
               max_in_flight: 1}}
    retry_initial_s: 0.2
    retry_max_s: 1.0
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [slb, archive], kinds: [detection]}}
"""
    )
    return config, archive


def simulate(tmp_path: Path, port: int, duration_s: int) -> subprocess.Popen[bytes]:
    scenario = tmp_path / "watch.yaml"
    scenario.write_text(SCENARIO.format(duration=duration_s))
    command = [*GATEWAY, "simulate", "--scenario", str(scenario), "--to"]
    command += [f"udp://127.0.0.1:{port}", "--resend-first", "0.5", "--resend-max", "2"]
    command += ["--linger", "20"]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def finish(simulator: subprocess.Popen[bytes]) -> dict[str, int]:
    stdout, stderr = simulator.communicate(timeout=120)
    assert simulator.returncode == 0, stderr.decode(errors="replace")
    match = SUMMARY.search(stdout.decode())
    assert match is not None, stdout.decode()
    return {k: int(v) for k, v in match.groupdict().items()}


def detection_numbers(event_ids: list[str]) -> list[int]:
    numbers = []
    for event_id in event_ids:
        match = DETECTION_ID.match(event_id)
        assert match is not None, event_id
        numbers.append(int(match.group(1)))
    return numbers


def at(start: float, offset_s: float) -> None:
    time.sleep(max(start + offset_s - time.monotonic(), 0.0))


@pytest.fixture(scope="module")
def outage(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    tmp_path = tmp_path_factory.mktemp("outage")
    gateway_port = free_udp_port()
    with (
        SlbPeer(tmp_path / "pki").in_thread() as peer,
        UdpCut(gateway_port) as radio,
    ):
        config, archive = write_node(tmp_path, peer, gateway_port)
        with running(config) as daemon:
            simulator = simulate(tmp_path, radio.port, duration_s=75)
            start = time.monotonic()
            at(start, 3)
            peer.down = True  # SLB unreachable for 60 s
            at(start, 15)
            radio.cut = True  # and the radio link gone for 30 s of it
            at(start, 45)
            radio.cut = False
            at(start, 63)
            peer.down = False
            line = finish(simulator)
            expected = list(range(1, line["sent"] + 1))
            wait_until(
                lambda: sorted(detection_numbers(list(peer.accepted))) == expected,
                30,
                "every detection in SLB",
            )
            circuit_opened = any(
                entry.get("circuit") == "open" for entry in daemon.events("sink_call_failed")
            )
            duplicates_dropped = daemon.metric(
                "fg_link_frames_ignored_total", reason="duplicate_detection"
            )
        archived = [e["event_id"] for e in archive_events(archive) if e["kind"] == "detection"]
        return {
            "line": line,
            "slb": list(peer.accepted),
            "duplicates": peer.duplicates,
            "refused_while_down": peer.refused_while_down,
            "archived": archived,
            "radio_dropped": radio.dropped,
            "circuit_opened": circuit_opened,
            "duplicates_dropped": duplicates_dropped,
        }


def test_slb_down_60_s_every_detection_arrives_once_in_order(outage: dict[str, Any]) -> None:
    line = outage["line"]
    assert line["sent"] >= 300  # 5 Hz for 75 s
    assert outage["refused_while_down"] > 0  # SLB really was unreachable
    assert outage["circuit_opened"]  # the sink's breaker opened, then closed again
    slb = outage["slb"]
    assert sorted(detection_numbers(slb)) == list(range(1, line["sent"] + 1))
    assert len(slb) == len(set(slb))  # each once (re-POSTs, if any, were answered 409)
    # In the order the gateway accepted them: the archive, a sink that was never down,
    # took them from the same spool in the same order.
    assert slb == outage["archived"]


def test_link_cut_30_s_every_detection_is_resent_acknowledged_and_kept_once(
    outage: dict[str, Any],
) -> None:
    line = outage["line"]
    assert outage["radio_dropped"] > 100  # detections and acknowledgements lost on the radio
    assert line["resent"] > 0
    assert (line["acknowledged"], line["unacknowledged"], line["dropped"]) == (line["sent"], 0, 0)
    archived = outage["archived"]
    assert len(archived) == len(set(archived)) == line["sent"]  # re-sends de-duplicated by id


def test_kill_9_mid_stream_loses_nothing_accepted(tmp_path: Path) -> None:
    gateway_port = free_udp_port()
    with SlbPeer(tmp_path / "pki").in_thread() as peer:
        peer.down = True
        config, _ = write_node(tmp_path, peer, gateway_port)
        first = Daemon(config)
        simulator = simulate(tmp_path, gateway_port, duration_s=20)
        try:
            # Mid-stream: once more than 20 detections were acknowledged (however long a
            # loaded machine takes to get there), with SLB owed everything so far.
            wait_until(
                lambda: first.metric("fg_detections_acknowledged_total") > 20,
                15,
                "21 detections acknowledged by the first gateway",
            )
            acknowledged_by_first = first.metric("fg_detections_acknowledged_total")
            first.kill9()
            time.sleep(5)  # 5 s without a gateway
            with running(config) as second:
                resumed = second.wait_event("spool_resumed", 5)
                time.sleep(3)
                peer.down = False
                line = finish(simulator)
                expected = list(range(1, line["sent"] + 1))
                wait_until(
                    lambda: sorted(detection_numbers(list(peer.accepted))) == expected,
                    30,
                    "every detection in SLB",
                )
        finally:
            if first.proc.poll() is None:
                first.kill9()
            if simulator.poll() is None:
                simulator.kill()
                simulator.wait()
    assert acknowledged_by_first > 20
    assert resumed["pending"]["slb"] >= acknowledged_by_first  # held across the SIGKILL
    assert line["refused"] > 0  # the airframe sent into the 5 s without a gateway
    assert (line["acknowledged"], line["unacknowledged"], line["dropped"]) == (line["sent"], 0, 0)
    assert sorted(detection_numbers(list(peer.accepted))) == list(range(1, line["sent"] + 1))
