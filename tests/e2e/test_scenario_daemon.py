"""A scenario through the real daemon: ``fischer-gateway simulate --scenario`` into ``run``.

Two airframes on one unsecured UDP link, a CoT UDP source and a jsonl archive; the simulator
plays a short scenario at four times real speed. The archive must hold detections from both
airframes with the scenario's classes and subtypes, and the friendly units' BlueForce events
with their callsigns. Loopback only.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.daemon_support import archive_events, free_udp_port, running, wait_until

SCENARIO = """\
name: e2e
duration_s: 8
seed: 1
airframes:
  - id: F26E-001
    sysid: 1
    orbit: {centre_lat_deg: 65.84, centre_lon_deg: 21.70, radius_m: 500, alt_msl_m: 600,
            speed_mps: 25}
    sensors:
      - {sensor: eo, range_m: 5000, confidence: 0.8, sigma_h_m: 10, rate_hz: 2}
  - id: F26E-002
    sysid: 2
    orbit: {centre_lat_deg: 65.83, centre_lon_deg: 21.72, radius_m: 500, alt_msl_m: 650,
            speed_mps: 25}
    sensors:
      - {sensor: ir, range_m: 5000, confidence: {loitering_munition: 0.75}, sigma_h_m: 15,
         rate_hz: 2}
targets:
  - id: LM-1
    class: loitering_munition
    subtype: LANCET-3
    speed_mps: 30
    path:
      - {lat_deg: 65.845, lon_deg: 21.75, alt_msl_m: 400}
      - {lat_deg: 65.8235, lon_deg: 21.6955, alt_msl_m: 45}
  - id: COL
    class: tank
    subtype: T-72B3
    speed_mps: 10
    column: {count: 2, spacing_m: 40}
    path:
      - {lat_deg: 65.86, lon_deg: 21.68, alt_msl_m: 60}
      - {lat_deg: 65.85, lon_deg: 21.69, alt_msl_m: 55}
blue_forces:
  - {uid: BLUE-1, callsign: VIDAR 1, position: {lat_deg: 65.8316, lon_deg: 21.7068,
     alt_msl_m: 42}, report_interval_s: 1}
  - {uid: BLUE-2, callsign: VIDAR 2, position: {lat_deg: 65.833, lon_deg: 21.645,
     alt_msl_m: 38}, report_interval_s: 2}
"""


def write_node(tmp_path: Path, link_port: int, cot_port: int) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - id: F26E-001
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{link_port}', security: unsecured, name: fleet}}]
  - id: F26E-002
    sysid: 2
    links: [{{uri: 'udp://127.0.0.1:{link_port}', security: unsecured, name: fleet}}]
sources:
  - {{name: cot_in, uri: 'udp://127.0.0.1:{cot_port}'}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive]}}
"""
    )
    return config, archive


def test_scenario_reaches_the_archive_through_the_daemon(tmp_path: Path) -> None:
    link_port, cot_port = free_udp_port(), free_udp_port()
    config, archive = write_node(tmp_path, link_port, cot_port)
    scenario = tmp_path / "e2e.yaml"
    scenario.write_text(SCENARIO)
    with running(config):  # returns once the daemon logged gateway_started: links bound
        target, cot = f"udp://127.0.0.1:{link_port}", f"udp://127.0.0.1:{cot_port}"
        command = [sys.executable, "-m", "gateway", "simulate", "--scenario", str(scenario)]
        command += ["--to", target, "--cot", cot, "--speed", "4"]
        simulate = subprocess.run(command, capture_output=True, timeout=30, check=False)
        assert simulate.returncode == 0, simulate.stderr.decode(errors="replace")

        def detections_seen() -> bool:
            kinds = {(e.get("kind"), e.get("airframe")) for e in archive_events(archive)}
            return {("detection", "F26E-001"), ("detection", "F26E-002")} <= kinds

        wait_until(detections_seen, 10.0, "detections from both airframes in the archive")
    events = archive_events(archive)
    seen = {
        (e["airframe"], e["sensor"], e["object_class"], e["subtype"], e["confidence"])
        for e in events
        if e["kind"] == "detection"
    }
    assert seen == {
        ("F26E-001", "eo", "loitering_munition", "LANCET-3", 0.8),
        ("F26E-001", "eo", "tank", "T-72B3", 0.8),
        ("F26E-002", "ir", "loitering_munition", "LANCET-3", 0.75),
    }
    blue = [e for e in events if e["kind"] == "blue_force"]
    assert {e["callsign"] for e in blue} == {"VIDAR 1", "VIDAR 2"}
    assert {e["uid"] for e in blue} == {"BLUE-1", "BLUE-2"}
    telemetry = {e.get("airframe") for e in events if e["kind"] == "telemetry"}
    assert telemetry >= {"F26E-001", "F26E-002"}


def test_simulate_help_tells_a_user_to_scale_the_fusion_speed_limits() -> None:
    """A node fed by ``simulate --speed X`` needs the fusion's ``speed_scale: X``: the user
    reading ``simulate --help`` learns it there, not only in docs/counter-uas.md."""
    shown = subprocess.run(
        [sys.executable, "-m", "gateway", "simulate", "--help"],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout
    assert "speed_scale: X" in " ".join(shown.split())
