"""A real MAVProxy, signing with its own passphrase, flies through a ``signed`` passthrough.

``fischer-gateway run`` holds one airframe: MAVSDK's own autopilot servers
(``MavsdkAutopilot``) on an unsecured link. Its passthrough has ``uplink: signed`` with the
key MAVProxy derives from its passphrase (SHA-256). MAVProxy — an independent MAVLink
implementation, which checks the signatures of what the gateway sends it — changes the mode
(DO_SET_MODE, PX4 AUTO/MISSION), uploads a three-item mission and is refused DO_SET_SERVO:
MAVProxy itself prints the DENIED answer, and the autopilot never sees the command.

MAVProxy is installed without its dependencies (over 1 GB, none needed here):
``pip install --no-deps mavproxy pyserial`` (``.ci/run`` does, and makes this test required).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from daemon_support import free_udp_port, running, wait_until, write_key
from mavsdk_autopilot import MavsdkAutopilot
from tools import need

pytestmark = pytest.mark.timeout(120)

PASSPHRASE = "boden-ground-station-1"  # noqa: S105 - the test station's passphrase
SERVO = 183
PX4_AUTO, PX4_MISSION = 4, 4


def mavproxy() -> str:
    beside = Path(sys.executable).parent / "mavproxy.py"
    if beside.exists():
        return str(beside)
    need("mavproxy.py")
    found = shutil.which("mavproxy.py")
    assert found is not None
    return found


class MavProxy:
    """MAVProxy as an operator runs it, commands typed on its console (stdin)."""

    def __init__(self, gcs_port: int, workdir: Path) -> None:
        self.proc = subprocess.Popen(
            [
                mavproxy(),
                f"--master=udpout:127.0.0.1:{gcs_port}",
                "--default-modules=signing,wp,mode,cmdlong,relay",
                "--state-basedir",
                str(workdir),
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={**os.environ, "MAVLINK20": "1"},
            cwd=workdir,
            text=True,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def type(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def said(self, text: str) -> bool:
        return any(text in line for line in list(self.lines))

    def stop(self) -> None:
        self.proc.kill()
        self.proc.wait(10)
        self._reader.join(5)
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe is not None:
                pipe.close()


@pytest.fixture
def station(tmp_path: Path) -> Iterator[tuple[MavProxy, MavsdkAutopilot, Path]]:
    mavproxy()  # skip early without it
    key = write_key(tmp_path / "gcs.key", hashlib.sha256(PASSPHRASE.encode()).digest())
    link, gcs_port = free_udp_port(), free_udp_port()
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - id: F26E-001
    sysid: 1
    passthrough: {{uri: 'udp://127.0.0.1:{gcs_port}', uplink: signed, key_file: '{key}'}}
    links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured}}]
"""
    )
    with running(config) as daemon, MavsdkAutopilot(link).running() as autopilot:
        proxy = MavProxy(gcs_port, tmp_path)
        try:
            yield proxy, autopilot, config
            assert daemon.proc.poll() is None
            (status,) = daemon.status()["passthroughs"]
            assert status["refused"]["effector"] == 1
            assert daemon.metric("fg_passthrough_refused_total", reason="effector") == 1
        finally:
            proxy.stop()


def test_mavproxy_changes_mode_and_uploads_a_mission_but_cannot_move_a_servo(
    station: tuple[MavProxy, MavsdkAutopilot, Path], tmp_path: Path
) -> None:
    proxy, autopilot, _config = station
    proxy.type(f"signing key {PASSPHRASE}")
    wait_until(lambda: proxy.said("Setup signing key"), 30, "MAVProxy's signing key set")
    # It hears the airframe only through frames the gateway signed with that key.
    wait_until(lambda: proxy.said("Detected vehicle 1:1"), 30, "MAVProxy detects the airframe")
    proxy.type(f"long DO_SET_MODE 1 {PX4_AUTO} {PX4_MISSION}")
    wait_until(lambda: "MISSION" in autopilot.flight_modes, 30, "the mode change at the autopilot")
    mission = tmp_path / "mission.txt"
    mission.write_text(
        "QGC WPL 110\n"
        "0\t1\t0\t16\t0\t0\t0\t0\t65.83\t21.00\t500\t1\n"
        "1\t0\t3\t16\t0\t0\t0\t0\t65.84\t21.01\t120\t1\n"
        "2\t0\t3\t16\t0\t0\t0\t0\t65.85\t21.02\t120\t1\n"
    )
    proxy.type(f"wp load {mission}")
    wait_until(lambda: bool(autopilot.missions), 30, "the mission at the autopilot")
    wait_until(lambda: proxy.said("TYPE_MISSION: ACCEPTED"), 30, "MAVProxy's MISSION_ACK")
    assert [(lat, lon) for _s, _c, lat, lon, _z in autopilot.missions[-1]] == [
        (65.83, 21.00),
        (65.84, 21.01),
        (65.85, 21.02),
    ]
    proxy.type("servo set 9 1900")
    wait_until(lambda: proxy.said("DO_SET_SERVO: DENIED"), 30, "the refusal answered")
    assert SERVO not in autopilot.uplink_commands
