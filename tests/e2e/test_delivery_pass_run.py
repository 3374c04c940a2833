"""Five CoT UDP sinks served by the delivery pass, through a kill -9, as an operator runs it.

``fischer-gateway simulate`` plays an airframe that re-sends every detection until it is
acknowledged; ``fischer-gateway run`` with a spool file feeds five CoT receivers over UDP,
whose sinks send in the loop pass's one delivery pass (``gateway.c2.deliverypass``) rather
than in their runners' tasks. The first gateway is killed with SIGKILL mid-stream and a second
starts on the same spool: every receiver must end with every detection the airframe sent,
the pass must have done the sending in both gateways, and nothing may be owed at the end.
Loopback only.
"""

from __future__ import annotations

import re
import selectors
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.daemon_support import Daemon, free_udp_port, running, wait_until

pytestmark = pytest.mark.timeout(120)

GATEWAY = [sys.executable, "-m", "gateway"]
SINKS = 5
UID = re.compile(rb'uid="fischer-det-[^"]*?-(\d+)-\d+"')
SUMMARY = re.compile(rb"detections sent (\d+), re-sent (\d+), acknowledged (\d+)")
#: One airframe watching a tank column at 5 Hz for 24 s of sim time (6 s at --speed 4).
SCENARIO = """\
name: pass
duration_s: 24
seed: 3
airframes:
  - id: F26E-001
    sysid: 1
    orbit: {centre_lat_deg: 65.84, centre_lon_deg: 21.70, radius_m: 500, alt_msl_m: 600,
            speed_mps: 25}
    sensors:
      - {sensor: eo, range_m: 8000, confidence: 0.8, sigma_h_m: 10, rate_hz: 5}
targets:
  - id: COL
    class: tank
    subtype: T-72B3
    speed_mps: 5
    path:
      - {lat_deg: 65.85, lon_deg: 21.70, alt_msl_m: 60}
      - {lat_deg: 65.86, lon_deg: 21.71, alt_msl_m: 60}
"""


def write_node(tmp_path: Path, link: int, receivers: list[int]) -> Path:
    sinks = "\n".join(
        f"  - {{name: cot{i}, type: cot, options: {{destinations: ['udp://127.0.0.1:{port}']}}}}"
        for i, port in enumerate(receivers)
    )
    names = ", ".join(f"cot{i}" for i in range(len(receivers)))
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
spool: {{path: '{tmp_path / "spool.db"}'}}
airframes:
  - id: F26E-001
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured, name: fleet}}]
sinks:
{sinks}
routes:
  - {{sinks: [{names}], kinds: [detection]}}
"""
    )
    return config


class Receivers:
    """Five UDP sockets read by a thread: the detection id of every CoT event on each."""

    def __init__(self, count: int) -> None:
        self.socks = []
        for _ in range(count):
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
            sock.setblocking(False)
            self.socks.append(sock)
        self.got: list[list[int]] = [[] for _ in self.socks]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    @property
    def ports(self) -> list[int]:
        return [sock.getsockname()[1] for sock in self.socks]

    def _read(self) -> None:
        with selectors.DefaultSelector() as selector:
            for index, sock in enumerate(self.socks):
                selector.register(sock, selectors.EVENT_READ, index)
            while not self._stop.is_set():
                for key, _ in selector.select(timeout=0.05):
                    sock, got = self.socks[key.data], self.got[key.data]
                    while True:
                        try:
                            data = sock.recv(65_535)
                        except BlockingIOError:
                            break
                        got.extend(int(n) for n in UID.findall(data))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for sock in self.socks:
            sock.close()


def sent_in_pass(daemon: Daemon) -> list[int]:
    return [int(sink["sent_in_pass"]) for sink in daemon.status()["sinks"]]


def test_kill_9_mid_stream_every_receiver_gets_every_detection(tmp_path: Path) -> None:
    receivers = Receivers(SINKS)
    link = free_udp_port()
    config = write_node(tmp_path, link, receivers.ports)
    scenario = tmp_path / "pass.yaml"
    scenario.write_text(SCENARIO)
    command = [*GATEWAY, "simulate", "--scenario", str(scenario), "--to"]
    command += [f"udp://127.0.0.1:{link}", "--speed", "4"]
    command += ["--resend-first", "0.2", "--resend-max", "0.5", "--linger", "15"]
    first = Daemon(config)
    simulator = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        wait_until(
            lambda: first.metric("fg_detections_acknowledged_total", result="held") >= 15,
            30,
            "15 detections held by the first gateway",
        )
        first_pass = sent_in_pass(first)
        first.kill9()
        time.sleep(0.5)
        with running(config) as second:
            stdout, stderr = simulator.communicate(timeout=60)
            assert simulator.returncode == 0, stderr.decode(errors="replace")
            (summary,) = SUMMARY.findall(stdout)
            sent = int(summary[0])
            expected = set(range(1, sent + 1))
            wait_until(
                lambda: all(set(got) >= expected for got in receivers.got),
                30,
                "every detection at every receiver",
            )
            wait_until(lambda: second.metric("fg_spool_pending_events") == 0, 10, "nothing owed")
            second_pass = sent_in_pass(second)
    finally:
        if first.proc.poll() is None:
            first.kill9()
        if simulator.poll() is None:
            simulator.kill()
            simulator.wait()
        receivers.close()
    assert int(summary[2]) == sent  # the airframe heard every detection acknowledged
    for got in receivers.got:
        assert set(got) == expected
        # Only what was sent and not yet confirmed when the first gateway died comes twice.
        assert len(got) - len(expected) < sent // 2
    assert all(n > 0 for n in first_pass)  # the delivery pass did the sending, in both
    assert all(n > 0 for n in second_pass)
