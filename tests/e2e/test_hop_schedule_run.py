"""Hop schedules the way operators run them: ``fischer-gateway run`` with a ``hop_plan`` and
``fischer-gateway simulate`` as separate processes on loopback.

The simulated airframe drops the first upload unanswered (a lost ACK), so the gateway must
send the schedule again; once accepted, the airframe's hop reports must reach the jsonl
archive as ``hop`` events and the upload state and hop counts must show on /status and
/metrics. Plain and in the tunnel (day keys made by ``fischer-gateway keys derive``). A plan
the airframe refuses shows as refused, sent once, with no hop events.
"""

from __future__ import annotations

import hashlib
import re
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest

from tests.daemon_support import archive_events, free_udp_port, running, wait_until, write_key

pytestmark = pytest.mark.timeout(90)

GATEWAY = [sys.executable, "-m", "gateway"]
MASTER = hashlib.sha256(b"hop-schedule e2e master").digest()
HOP_LINE = re.compile(
    r"^airframe 1 \(sysid 1\): hop schedules received (?P<received>\d+), active "
    r"(?P<active>[0-9a-f]{8}), hop reports (?P<reports>\d+)$",
    re.MULTILINE,
)


def write_node(tmp_path: Path, port: int, security: str) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    tunnel = ""
    if security == "tunnel":
        tunnel = f"tunnel: {{master_key_file: '{write_key(tmp_path / 'master.key', MASTER)}'}}"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
{tunnel}
airframes:
  - id: F26E-001
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{port}', security: {security}, name: fleet}}]
    hop_plan:
      frequencies_mhz: [2405.0, 2430.5, 2455.0, 5805.0]
      bandwidth_mhz: 10
      dwell_us: 12
      jammer_reaction_us: 20
      ack_timeout_s: 0.5
      retry_max_s: 2
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive], kinds: [hop]}}
"""
    )
    return config, archive


def simulate(port: int, *extra: str) -> subprocess.CompletedProcess[bytes]:
    command = [*GATEWAY, "simulate", "--to", f"udp://127.0.0.1:{port}", "--airframes", "1"]
    command += ["--no-resend", "--linger", "0", *extra]
    return subprocess.run(command, capture_output=True, timeout=60, check=False)


def hops(archive: Path) -> list[dict[str, Any]]:
    return [e for e in archive_events(archive) if e["kind"] == "hop"]


def key_dir(tmp_path: Path) -> list[str]:
    """``simulate`` options sealing F26E-001's frames with keys derived as operators do."""
    master = write_key(tmp_path / "airframe-master.key", MASTER)
    today = datetime.now(UTC).date().isoformat()
    derive = [*GATEWAY, "keys", "derive", "--master", str(master), "--airframe", "F26E-001"]
    derive += ["--from", today, "--days", "2", "--out", str(tmp_path / "keys")]
    subprocess.run(derive, capture_output=True, timeout=30, check=True)
    return ["--key-dir", str(tmp_path / "keys"), "--airframe-id", "F26E-001"]


@pytest.mark.parametrize("security", ["unsecured", "tunnel"])
def test_a_lost_ack_is_retried_then_the_schedule_is_accepted_and_hops_are_archived(
    tmp_path: Path, security: str
) -> None:
    port = free_udp_port()
    config, archive = write_node(tmp_path, port, security)
    sealing = key_dir(tmp_path) if security == "tunnel" else []
    with running(config) as daemon:
        played = simulate(port, "--duration", "8", "--speed", "2", "--hop-ignore", "1", *sealing)
        assert played.returncode == 0, played.stderr.decode(errors="replace")
        wait_until(
            lambda: {"scheduled", "jammed"} <= {e["reason"] for e in hops(archive)}, 10, "hops"
        )
        (upload,) = daemon.status()["hop_schedules"]
        state = daemon.metric("fg_hop_schedule_state", airframe="F26E-001", state="accepted")
        sends = daemon.metric("fg_hop_schedule_sends_total", airframe="F26E-001")
        jammed = daemon.metric("fg_hop_events_total", airframe="F26E-001", reason="jammed")
        flown = daemon.metric("fg_hops_total", airframe="F26E-001")
    (line,) = HOP_LINE.finditer(played.stdout.decode())
    assert line["received"] == "2"  # the first went unanswered: the gateway sent it again
    assert (upload["state"], upload["sends"], upload["last_result"]) == ("accepted", 2, "accepted")
    assert upload["schedule_id"] == line["active"] == upload["active_schedule_id"]
    assert (state, sends) == (1.0, 2.0)
    events = hops(archive)
    assert {e["schedule_id"] for e in events} == {int(line["active"], 16)}
    assert all(e["is_gateway_schedule"] and e["airframe"] == "F26E-001" for e in events)
    assert {e["frequency_hz"] for e in events} <= {2405e6, 2430.5e6, 2455e6, 5805e6}
    assert jammed == len([e for e in events if e["reason"] == "jammed"]) >= 1
    # 12 µs dwell: some 80 000 hops a second, counted from the reports' hop counts.
    assert flown == max(e["hop_count"] for e in events) > 80_000


def test_a_refused_schedule_is_shown_and_not_sent_again(tmp_path: Path) -> None:
    port = free_udp_port()
    config, archive = write_node(tmp_path, port, "unsecured")
    with running(config) as daemon:
        played = simulate(port, "--duration", "3", "--hop-result", "unsupported_frequency")
        assert played.returncode == 0, played.stderr.decode(errors="replace")
        wait_until(lambda: daemon.status()["hop_schedules"][0]["state"] == "refused", 10, "refusal")
        (upload,) = daemon.status()["hop_schedules"]
        refused = daemon.metric(
            "fg_hop_schedule_answers_total", airframe="F26E-001", result="unsupported_frequency"
        )
        state = daemon.metric("fg_hop_schedule_state", airframe="F26E-001", state="refused")
        refusal = daemon.wait_event("hop_schedule_refused", 5)
    assert (upload["sends"], upload["last_result"]) == (1, "unsupported_frequency")
    assert upload["active_schedule_id"] == "00000000"
    assert (refused, state) == (1.0, 1.0)
    assert refusal["result"] == "unsupported_frequency"
    assert not hops(archive)


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (["--hop-ignore", "-1"], "--hop-ignore: expected 0 or more, got -1"),
        (
            ["--scenario", "t72-column", "--hop-result", "denied"],
            "--hop-result: applies to the demo fleet, not to a --scenario",
        ),
    ],
)
def test_simulate_refuses_hop_options_it_cannot_apply(extra: list[str], expected: str) -> None:
    command = [*GATEWAY, "simulate", "--to", f"udp://127.0.0.1:{free_udp_port()}", *extra]
    played = subprocess.run(command, capture_output=True, timeout=60, check=False)
    assert played.returncode == 2
    assert expected in played.stderr.decode()
