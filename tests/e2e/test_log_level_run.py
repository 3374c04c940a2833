"""``gateway.log_level`` holds for every logger of the daemon, those bound before it too.

``fischer-gateway run`` logs at ``info`` while it reads the config, and checking a sink's
options builds the sink, which binds its logger then. Before the fix those loggers kept
``info`` whatever the config said: an ``slb`` sink at ``log_level: warning`` still wrote
``slb_items_delivered`` for every batch. Here a daemon at ``warning`` delivers detections to
a real HTTPS SLB whose first POSTs fail: the failures are logged (warning and above pass),
no line below warning is.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Airframe, free_tcp_port, free_udp_port, wait_until
from slb_peer import SlbPeer

pytestmark = pytest.mark.timeout(60)

DETECTIONS = 5


def test_log_level_warning_holds_for_sinks_bound_while_the_config_was_read(
    tmp_path: Path,
) -> None:
    link, health = free_udp_port(), free_tcp_port()
    with SlbPeer(tmp_path / "pki", fail_first=2).in_thread() as peer:
        options = json.dumps(peer.sink_options())
        config = tmp_path / "node.yaml"
        config.write_text(
            f"""
gateway: {{shutdown_deadline_s: 3, log_level: warning}}
health: {{port: {health}}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}
sinks:
  - {{name: slb, type: slb, options: {options}, retry_initial_s: 0.1, retry_max_s: 0.2}}
routes:
  - {{sinks: [slb], kinds: [detection]}}
"""
        )
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", "run", "--config", str(config)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        lines: list[str] = []
        reader = threading.Thread(
            target=lambda: lines.extend(
                raw.decode("utf-8", "replace") for raw in proc.stdout or ()
            ),
            daemon=True,
        )
        reader.start()
        try:
            airframe = Airframe(1)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:

                def delivered() -> bool:
                    assert proc.poll() is None, "".join(lines[-20:])
                    if airframe.detections < 500:  # until the daemon listens, then a few more
                        sock.sendto(airframe.heartbeat(), ("127.0.0.1", link))
                        sock.sendto(airframe.detection(), ("127.0.0.1", link))
                    return len(peer.accepted) >= DETECTIONS

                wait_until(delivered, 45.0, f"{DETECTIONS} object items at SLB")
        finally:
            proc.terminate()
            proc.wait(timeout=15)
            reader.join(timeout=5)
            if proc.stdout is not None:
                proc.stdout.close()
    logged: list[dict[str, Any]] = [json.loads(line.lstrip("<0123456789>")) for line in lines]
    levels = {entry["level"] for entry in logged}
    assert "warning" in levels or "error" in levels, logged  # the 503s: warnings do pass
    below = [entry for entry in logged if entry["level"] in {"debug", "info"}]
    assert below == [], below
