"""An order that survives kill -9 of the daemon twice: mid-upload and mid-execution.

``fischer-gateway run`` (a spool file, the ``orders`` processor, the ``local`` order source,
a jsonl archive) and ``fischer-gateway simulate`` beside it, as an operator runs them.

1. The simulator is stopped (SIGSTOP) and the order sent: accepted, its upload waits for
   the airframe's answers; the daemon is killed (SIGKILL) with the upload under way.
2. The daemon starts again on the same spool and the simulator goes on (SIGCONT): the
   order's upload starts over, and the order goes to ``executing``.
3. Killed again while the airframe flies to the point; started again: the daemon reads the
   airframe's mission back, finds it is the order's, and the order goes on to ``completed``
   (no second upload).

Every status reaches the issuer: what the ``fischer-gateway order`` client heard before its
daemon died, then ``fischer-gateway order --status ID``, de-duplicated by ``seq``, is
accepted, executing, completed, each exactly once, the same under each ``seq`` wherever it
was seen; the archive (statuses published again after each restart) holds the same.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Daemon, archive_events, free_udp_port, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(150)]

#: 2.6 km from the simulated airframe's orbit: some 12 s of flight at ten times real time,
#: the room to kill the daemon on the way (before the last item is reached).
POINT = (65.8400, 21.7400)
ALT_MSL_M = 320.0
ORDER_ID = "RESTART-1"
SPEED = 10.0


def write_config(tmp_path: Path, link: int, sock: Path) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
spool: {{path: '{tmp_path / "spool.db"}'}}
airframes:
  - {{id: F26E-001, sysid: 1, autopilot: px4, link_timeout_s: 60,
     links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured, name: fleet}}]}}
sources:
  - {{name: operator, type: local, socket: '{sock}'}}
processors:
  - name: orders
    type: orders
    options: {{time_on_task_s: 2, loiter_radius_m: 250, mission_timeout_s: 3,
               mission_retries: 3}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive], kinds: [order_status, telemetry]}}
"""
    )
    return config, archive


def order_cli(sock: Path, *args: str) -> tuple[int, list[dict[str, Any]], str]:
    command = [sys.executable, "-m", "gateway", "order", "--socket", str(sock), *args]
    done = subprocess.run(command, capture_output=True, timeout=60, check=False)
    lines = [json.loads(line) for line in done.stdout.decode().splitlines() if line.strip()]
    return done.returncode, lines, done.stderr.decode(errors="replace")


def statuses(archive: Path) -> list[dict[str, Any]]:
    return [e for e in archive_events(archive, torn=True) if e["kind"] == "order_status"]


def has(archive: Path, status: str) -> bool:
    return any(e["status"] == status for e in statuses(archive))


def by_seq(lines: list[dict[str, Any]]) -> dict[int, str]:
    """Statuses by ``seq``; every copy of one ``seq`` says the same."""
    seen: dict[int, str] = {}
    for line in lines:
        if line.get("seq") is None:
            continue  # "received": the local source's own answer, no status of the processor
        assert seen.setdefault(line["seq"], line["status"]) == line["status"], line
    return seen


def test_an_order_continues_after_kill_9_mid_upload_and_mid_execution(tmp_path: Path) -> None:
    link = free_udp_port()
    sock = tmp_path / "orders.sock"
    config, archive = write_config(tmp_path, link, sock)
    command = [
        sys.executable, "-m", "gateway", "simulate", "--to", f"udp://127.0.0.1:{link}",
        "--airframes", "1", "--autopilot", "px4", "--speed", str(SPEED), "--no-resend",
    ]  # fmt: skip
    sim = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    daemons: list[Daemon] = []
    try:
        daemons.append(Daemon(config))
        wait_until(
            lambda: any(
                e["kind"] == "telemetry" and e["endurance_remaining_min"]
                for e in archive_events(archive, torn=True)
            ),
            30.0,
            "the simulated airframe's telemetry",
        )
        # 1. The airframe falls silent (its link stays up for link_timeout_s): the upload
        # waits for its answers, and the daemon dies under it.
        sim.send_signal(signal.SIGSTOP)
        code, client, stderr = order_cli(
            sock, "--task", "observe_point", "--airframe", "F26E-001", "--order-id", ORDER_ID,
            "--point", str(POINT[0]), str(POINT[1]), "--alt-msl-m", str(ALT_MSL_M),
        )  # fmt: skip
        assert code == 0, stderr
        assert [line["status"] for line in client] == ["received", "accepted"]
        wait_until(lambda: has(archive, "accepted"), 10.0, "accepted archived")
        daemons[-1].kill9()
        # 2. Started again: the upload starts over once the airframe is heard.
        daemons.append(Daemon(config))
        sim.send_signal(signal.SIGCONT)
        wait_until(lambda: has(archive, "executing"), 30.0, "executing after the restart")
        assert not has(archive, "completed")
        daemons[-1].kill9()
        # 3. Killed on the way to the point; started again: the mission is read back.
        daemons.append(Daemon(config))
        wait_until(lambda: has(archive, "completed"), 60.0, "completed after the restart")
        # Logged once the mission read back was found to be the order's (nothing uploaded).
        resumed = daemons[-1].wait_event("order_resumed", 5.0)
        assert resumed["order_id"] == ORDER_ID
        code, kept, stderr = order_cli(sock, "--status", ORDER_ID)
        assert code == 0, stderr
        assert not has(archive, "failed")
    finally:
        sim.send_signal(signal.SIGCONT)
        for daemon in daemons:
            daemon.stop()
        sim.terminate()
        sim.wait(timeout=10)
    expected = {1: "accepted", 2: "executing", 3: "completed"}
    # The issuer: what the client heard, then what --status answered, once each by seq.
    assert by_seq(client + kept) == expected
    assert [line["seq"] for line in kept] == [1, 2, 3]
    # The archive: the statuses published again after each restart, the same by seq.
    archived = statuses(archive)
    assert by_seq(archived) == expected
    assert {e["order_id"] for e in archived} == {ORDER_ID}
    # At least once: the accepted status went out again after each restart.
    assert sum(1 for e in archived if e["seq"] == 1) >= 3
