"""A hostile airframe and a hostile local operator against the orders processor, through ``run``.

``fischer-gateway run --config FILE`` in a child process with one airframe on an unsecured
loopback UDP link, the ``orders`` processor and the ``local`` order source. The airframe is a
pymavlink peer in this process that answers the mission protocol as an attacker would: it asks
for mission items that do not exist, then reports items far past the end of the mission as
reached and current, and the mission's own last item reached and one past it current while it
is a kilometre away. An order must never be reported ``completed`` on such reports: only the
items the gateway uploaded count, and only with the airframe's position there.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from daemon_support import free_udp_port, running, wait_until
from pymavlink.dialects.v20 import common as mav

pytestmark = pytest.mark.timeout(120)


class HostileAirframe:
    """Telemetry for the checks, and hostile answers to the gateway's mission protocol."""

    def __init__(self, gateway_port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.gateway = ("127.0.0.1", gateway_port)
        self.mav = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = mav.MAVLink(None)
        self.uplink: list[Any] = []
        self.bogus_progress = True
        #: Answer MISSION_COUNT with MISSION_ACK ACCEPTED at once, asking for no item.
        self.early_ack = False
        #: Answer MISSION_COUNT with this MAV_MISSION_RESULT error instead.
        self.ack_error: int | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def send(self, msg: Any) -> None:
        self.sock.sendto(bytes(msg.pack(self.mav)), self.gateway)

    def _telemetry(self) -> None:
        self.send(mav.MAVLink_heartbeat_message(2, 12, 128 | 1, 0, 4, 3))
        self.send(
            mav.MAVLink_global_position_int_message(
                0, 658_300_000, 210_000_000, 500_000, 400_000, 0, 0, 0, 0
            )
        )
        self.send(mav.MAVLink_sys_status_message(0, 0, 0, 500, 16000, 1000, 80, 0, 0, 0, 0, 0, 0))

    def _answer(self, msg: Any) -> None:
        name = msg.get_type()
        self.uplink.append(msg)
        if name == "MISSION_COUNT" and (self.early_ack or self.ack_error is not None):
            answer = 0 if self.ack_error is None else self.ack_error
            self.send(mav.MAVLink_mission_ack_message(255, 191, answer, 0))
        elif name == "MISSION_COUNT":
            # Items that do not exist first, then the real ones.
            for seq in (65535, msg.count, msg.count + 7, *range(msg.count)):
                self.send(mav.MAVLink_mission_request_int_message(255, 191, seq, 0))
        elif name == "MISSION_ITEM_INT" and msg.seq == max(0, self._count() - 1):
            self.send(mav.MAVLink_mission_ack_message(255, 191, 0, 0))
        elif name == "COMMAND_LONG":
            self.send(mav.MAVLink_command_ack_message(msg.command, 0))
            if self.bogus_progress:
                for _ in range(200):  # items that were never uploaded
                    self.send(mav.MAVLink_mission_item_reached_message(60000))
                    self.send(mav.MAVLink_mission_current_message(4000))
                    self.send(mav.MAVLink_command_ack_message(400, 0))  # never sent
                # "Done": the last item reached, one past it current; it never left home.
                self.send(mav.MAVLink_mission_item_reached_message(self._count() - 1))
                self.send(mav.MAVLink_mission_current_message(self._count()))

    def _count(self) -> int:
        counts = [m.count for m in self.uplink if m.get_type() == "MISSION_COUNT"]
        return counts[-1] if counts else 0

    def _run(self) -> None:
        last = 0.0
        while not self._stop.is_set():
            if time.monotonic() - last > 0.2:
                self._telemetry()
                last = time.monotonic()
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            for byte in data:
                try:
                    msg = self.parser.parse_char(bytes([byte]))
                except mav.MAVError:
                    continue
                if msg is not None:
                    self._answer(msg)

    def __enter__(self) -> HostileAirframe:
        self._thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.sock.close()


def write_config(tmp_path: Path, link: int, sock: Path) -> Path:
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}
sources:
  - {{name: operator, type: local, socket: '{sock}', socket_mode: 0666}}
processors:
  - {{name: orders, type: orders, options: {{time_on_task_s: 5, mission_timeout_s: 1,
      command_timeout_s: 1, command_retries: 0}}}}
"""
    )
    return config


def order_cli(sock: Path, *args: str, timeout: str = "8") -> tuple[int, list[dict[str, Any]]]:
    command = [sys.executable, "-m", "gateway", "order", "--socket", str(sock), "--timeout"]
    done = subprocess.run([*command, timeout, *args], capture_output=True, timeout=60, check=False)
    lines = [json.loads(line) for line in done.stdout.decode().splitlines() if line.strip()]
    return done.returncode, lines


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, HostileAirframe, Path]]:
    tmp_path = tmp_path_factory.mktemp("order-attacks")
    link = free_udp_port()
    # A directory other uids may traverse (pytest's is 0700), for the peer-credentials test.
    open_dir = Path(tempfile.mkdtemp(prefix="fg-orders-"))
    open_dir.chmod(0o755)
    sock = open_dir / "orders.sock"
    with running(write_config(tmp_path, link, sock)) as daemon, HostileAirframe(link) as airframe:
        wait_until(
            lambda: daemon.status()["airframes"][0].get("active_link") is not None,
            30.0,
            "the airframe linked",
        )
        yield daemon, airframe, sock
    shutil.rmtree(open_dir, ignore_errors=True)


def test_progress_for_items_never_uploaded_does_not_complete_the_order(
    node: tuple[Any, HostileAirframe, Path],
) -> None:
    daemon, airframe, sock = node
    code, lines = order_cli(
        sock,
        "--task",
        "observe_point",
        "--point",
        "65.84",
        "21.01",
        "--follow",
        "--airframe",
        "F26E-001",
        "--order-id",
        "BOGUS-1",
        timeout="4",
    )
    statuses = [line["status"] for line in lines]
    assert statuses == ["received", "accepted", "executing"], lines[-1]
    assert code == 2  # still executing: no honest completion came
    sent = [m.seq for m in airframe.uplink if m.get_type() == "MISSION_ITEM_INT"]
    assert sorted(set(sent)) == [0, 1]  # never an item that does not exist
    assert len(daemon.events("command_ack_unexpected")) <= 2
    processors = json.dumps(daemon.status())
    assert '"progress_ignored"' in processors
    # 600 hostile frames: counted, not a log line each.
    names = [line.get("event") for line in list(daemon.lines)]
    assert max(names.count(name) for name in set(names)) < 20, sorted(set(names))


def test_replayed_order_id_with_other_content_is_answered(
    node: tuple[Any, HostileAirframe, Path],
) -> None:
    _daemon, _airframe, sock = node
    first = ("--task", "observe_point", "--airframe", "F26E-001", "--order-id", "REPLAY-1")
    code, lines = order_cli(sock, *first, "--point", "65.84", "21.01", timeout="6")
    assert [line["status"] for line in lines] == ["received", "accepted"], lines
    code, lines = order_cli(sock, *first, "--point", "65.80", "21.30", timeout="6")
    assert code == 1, lines
    assert lines[-1]["status"] == "conflict"
    assert lines[-1]["reason"].startswith("order_id: REPLAY-1 was already taken with other")
    code, lines = order_cli(sock, *first, "--point", "65.84", "21.01", timeout="6")
    assert code == 1, lines  # the same order again: taken once
    assert lines[-1]["status"] == "rejected"


def test_clients_that_hang_up_free_their_connection(tmp_path: Path) -> None:
    # No orders processor: nothing ever answers beyond "received", so only the hang-up frees
    # a connection. Three clients give up in turn; a fourth must still be served.
    sock = tmp_path / "orders.sock"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{free_udp_port()}',
     security: unsecured, name: fleet}}]}}
sources:
  - {{name: operator, type: local, socket: '{sock}', max_connections: 2}}
"""
    )
    with running(config):
        wait_until(sock.exists, 10.0, "the socket")
        for n in range(4):
            code, lines = order_cli(
                sock,
                "--task",
                "return_to_base",
                "--mgrs",
                "34WDA1234567890",
                "--order-id",
                f"GONE-{n}",
                timeout="1",
            )
            assert code == 2
            assert [line["status"] for line in lines] == ["received"], (n, lines)


def as_nobody(sock: Path, payload: bytes) -> bytes:
    """What a process of uid 65534 (not the daemon's, not allowed) reads back after sending."""
    script = (
        "import os, socket, sys\n"
        "os.setgid(65534); os.setuid(65534)\n"
        "s = socket.socket(socket.AF_UNIX); s.settimeout(10); s.connect(sys.argv[1])\n"
        "try:\n"
        "    s.sendall(sys.stdin.buffer.read()); sys.stdout.buffer.write(s.recv(65536))\n"
        "except (BrokenPipeError, ConnectionResetError):\n"
        "    pass  # closed unanswered\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, str(sock)], input=payload, capture_output=True, timeout=30
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


@pytest.mark.skipif(not hasattr(socket, "SO_PEERCRED"), reason="Linux peer credentials")
def test_a_peer_of_another_uid_is_closed_unanswered(
    node: tuple[Any, HostileAirframe, Path],
) -> None:
    if os.geteuid() != 0:
        pytest.skip("needs root to act as another uid")
    daemon, airframe, sock = node
    order = {
        "order_id": "NOBODY-1",
        "issuer": "x",
        "issued": "2026-11-22T12:00:00Z",
        "task": "return_to_base",
        "location": {"mgrs": "34WDA1234567890"},
        "priority": "flash",
    }
    before = len(airframe.uplink)
    # The socket is 0666 in this config: only the peer credentials keep uid 65534 out.
    assert as_nobody(sock, json.dumps(order).encode() + b"\n") == b""
    assert '"refused_peer": 1' in json.dumps(daemon.status())
    assert len(airframe.uplink) == before


def raw_order(sock: Path, order: dict[str, Any]) -> list[dict[str, Any]]:
    """Send ``order`` as the command would and read the answers until a final one."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as raw:
        raw.settimeout(10)
        raw.connect(str(sock))
        raw.sendall(json.dumps(order).encode() + b"\n")
        lines = []
        for line in raw.makefile("rb"):
            lines.append(json.loads(line))
            if lines[-1]["status"] in ("rejected", "accepted", "failed", "completed"):
                break
        return lines


def test_hostile_order_shapes_and_windows_are_rejected_with_their_reason(
    node: tuple[Any, HostileAirframe, Path],
) -> None:
    _daemon, airframe, sock = node
    before = len(airframe.uplink)
    bow_tie = ["65.80,21.00", "65.90,21.10", "65.90,21.00", "65.80,21.10"]
    code, lines = order_cli(
        sock, "--task", "recon_area", "--airframe", "F26E-001", "--polygon", *bow_tie
    )
    assert code == 1
    assert (lines[-1]["status"], lines[-1]["check"]) == ("rejected", "area")
    assert lines[-1]["reason"] == "the order's polygon crosses itself: edge 1-2 crosses edge 3-4"
    later = {
        "order_id": "LATER-1",
        "issuer": "x",
        "issued": "2026-11-22T12:00:00Z",
        "task": "observe_point",
        "airframe": "F26E-001",
        "location": {"point": {"lat_deg": 65.84, "lon_deg": 21.01}},
        "priority": "routine",
        "not_before": "2999-01-01T00:00:00Z",
    }
    lines = raw_order(sock, later)
    assert (lines[-1]["status"], lines[-1]["check"]) == ("rejected", "window")
    nan = {**later, "order_id": "NAN-1", "not_before": None}
    nan["location"] = {"point": {"lat_deg": float("nan"), "lon_deg": 21.0}}
    assert raw_order(sock, {k: v for k, v in nan.items() if v is not None}) == [
        {"status": "rejected", "reason": "order: NaN is not JSON"}
    ]
    assert "at most 3600 s ahead" in lines[-1]["reason"]
    assert len(airframe.uplink) == before  # nothing reached the airframe


def test_check_config_names_a_fence_that_crosses_itself_with_key_and_line(
    tmp_path: Path,
) -> None:
    config = tmp_path / "node.yaml"
    config.write_text(
        """processors:
  - name: orders
    type: orders
    options:
      geofence:
        - {lat_deg: 65.0, lon_deg: 20.0}
        - {lat_deg: 67.0, lon_deg: 24.0}
        - {lat_deg: 65.0, lon_deg: 24.0}
        - {lat_deg: 67.0, lon_deg: 20.0}
"""
    )
    command = [sys.executable, "-m", "gateway", "check-config", "--no-environment", str(config)]
    done = subprocess.run(command, capture_output=True, timeout=60, check=False)
    assert done.returncode == 2
    assert (
        f"{config}:5 processors[0].options.geofence: the fence crosses itself:"
        " edge 1-2 crosses edge 3-4"
    ) in done.stdout.decode() + done.stderr.decode()


def test_the_loop_logged_no_error_through_all_of_it(
    node: tuple[Any, HostileAirframe, Path],
) -> None:
    daemon, _airframe, sock = node
    for n in range(5):  # final answers and hang-ups in quick succession
        code, _lines = order_cli(
            sock,
            "--task",
            "observe_point",
            "--airframe",
            "F26E-404",
            "--point",
            "65.84",
            "21.01",
            "--order-id",
            f"LAST-{n}",
        )
        assert code == 1
    assert daemon.proc.poll() is None
    assert daemon.events("asyncio_error") == []


def test_a_mission_acknowledged_without_its_items_is_not_executing(
    node: tuple[Any, HostileAirframe, Path],
) -> None:
    _daemon, airframe, sock = node
    airframe.early_ack = True
    try:
        code, lines = order_cli(
            sock,
            "--task",
            "observe_point",
            "--airframe",
            "F26E-001",
            "--point",
            "65.84",
            "21.01",
            "--order-id",
            "EARLY-1",
            "--follow",
        )
    finally:
        airframe.early_ack = False
    assert code == 1, lines
    assert (lines[-1]["status"], lines[-1]["check"]) == ("failed", "mission")
    assert lines[-1]["reason"] == (
        "mission upload: MAV_MISSION_ACCEPTED without asking for items 0, 1"
    )


def refused_for_room(daemon: Any) -> int:
    (source,) = [s for s in daemon.status()["sources"] if s.get("type") == "local"]
    return int(source["counts"].get("too_many_connections", 0))


def test_oversized_and_idle_connections_are_answered_and_bounded(
    node: tuple[Any, HostileAirframe, Path],
) -> None:
    daemon, _airframe, sock = node
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as big:
        big.settimeout(10)
        big.connect(str(sock))
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):
            big.sendall(b"{" + b" " * 70_000)
        answer = json.loads(big.makefile("rb").readline())
    assert answer == {
        "status": "rejected",
        "reason": "order: no end of line within max_line_bytes (65536)",
    }
    idle = []
    try:
        for _ in range(40):  # beyond max_connections (8): the rest are closed at once
            conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            conn.connect(str(sock))
            idle.append(conn)
        wait_until(
            lambda: refused_for_room(daemon) >= 32,
            10.0,
            "the connections over the cap closed and counted",
        )
    finally:
        for conn in idle:
            conn.close()
    assert daemon.proc.poll() is None


def test_an_operator_window_that_is_over_is_rejected(
    node: tuple[Any, HostileAirframe, Path],
) -> None:
    _daemon, _airframe, sock = node
    code, lines = order_cli(
        sock,
        "--task",
        "track_target",
        "--airframe",
        "F26E-001",
        "--point",
        "65.84",
        "21.01",
        "--track-id",
        "trk-none",
        "--not-after",
        "2020-01-01T00:00:00Z",
        "--order-id",
        "PAST-1",
    )
    assert code == 1
    assert (lines[-1]["status"], lines[-1]["check"]) == ("rejected", "window")
    assert lines[-1]["reason"].startswith("the window ended at 2020-01-01T00:00:00+00:00")


def test_a_mission_the_airframe_refuses_fails_with_its_result(
    node: tuple[Any, HostileAirframe, Path],
) -> None:
    _daemon, airframe, sock = node
    airframe.ack_error = mav.MAV_MISSION_NO_SPACE
    try:
        code, lines = order_cli(
            sock,
            "--task",
            "recon_area",
            "--airframe",
            "F26E-001",
            "--order-id",
            "NOSPACE-1",
            "--polygon",
            "65.84,21.02",
            "65.84,21.06",
            "65.86,21.06",
            "--follow",
        )
    finally:
        airframe.ack_error = None
    assert code == 1, lines
    assert (lines[-1]["status"], lines[-1]["check"]) == ("failed", "mission")
    assert lines[-1]["reason"] == "mission upload: MAV_MISSION_NO_SPACE"


def test_a_fence_for_an_airframe_id_that_is_not_configured_is_refused(tmp_path: Path) -> None:
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{free_udp_port()}',
     security: unsecured, name: fleet}}]}}
processors:
  - name: orders
    type: orders
    options:
      airframe_geofences:
        F26E-01:
          - {{lat_deg: 65.0, lon_deg: 20.0}}
          - {{lat_deg: 65.0, lon_deg: 24.0}}
          - {{lat_deg: 67.0, lon_deg: 20.0}}
"""
    )
    expected = (
        f"{config}:9 processors[0].options.airframe_geofences.F26E-01: 'F26E-01' is not an"
        " airframe of this config (airframes: F26E-001)"
    )
    for command in (
        ["check-config", "--no-environment", str(config)],
        ["run", "--config", str(config)],
    ):
        done = subprocess.run(
            [sys.executable, "-m", "gateway", *command],
            capture_output=True,
            timeout=60,
            check=False,
        )
        assert done.returncode == 2
        assert expected in done.stdout.decode() + done.stderr.decode()


def test_clients_gone_as_their_status_comes_end_only_their_connections(tmp_path: Path) -> None:
    """Clients that read ``received`` and hang up at once, as the processor's ``waiting``
    comes (the airframe is not heard): writing it fails before the hang-up is seen. Each
    such client ends only its own connection; the source never fails (it did, and its
    socket vanished while it restarted), and the statuses are kept for ``--status``."""
    link = free_udp_port()
    sock = tmp_path / "orders.sock"
    with running(write_config(tmp_path, link, sock)) as daemon:
        wait_until(sock.exists, 10.0, "the socket")
        for n in range(100):
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as raw:
                raw.settimeout(10)
                raw.connect(str(sock))
                order = {
                    "order_id": f"HANGUP-{n}",
                    "issued": "2026-11-22T12:00:00Z",
                    "airframe": "F26E-001",
                    "task": "observe_point",
                    "location": {"point": {"lat_deg": 65.84, "lon_deg": 21.01}},
                }
                raw.sendall(json.dumps(order).encode() + b"\n")
                assert b'"received"' in raw.recv(65536)
        code, lines = order_cli(
            sock, "--task", "observe_point", "--point", "65.84", "21.01", "--airframe",
            "F26E-001", "--order-id", "AFTER-1",
        )  # fmt: skip
        assert code == 3, lines  # waiting: the source still serves
        code, lines = order_cli(sock, "--status", "HANGUP-99")
        assert code == 0, lines
        assert [line["status"] for line in lines] == ["waiting"]
        assert daemon.events("source_failed") == []
        assert '"client_gone"' in json.dumps(daemon.status())


class SlowToIdentify(HostileAirframe):
    """An ArduPlane whose position and battery state come before its first HEARTBEAT (as
    after a restart of the node, or as the link comes up), and which answers honestly."""

    def __init__(self, gateway_port: int) -> None:
        super().__init__(gateway_port)
        self.bogus_progress = False
        self.identified = threading.Event()
        self.uplink_before_heartbeat: list[str] = []

    def _telemetry(self) -> None:
        if self.identified.is_set():  # ArduPilot (3), fixed wing (1), in GUIDED (15)
            self.send(mav.MAVLink_heartbeat_message(1, 3, 128 | 1, 15, 4, 3))
        self.send(
            mav.MAVLink_global_position_int_message(
                0, 658_300_000, 210_000_000, 500_000, 400_000, 0, 0, 0, 0
            )
        )
        self.send(mav.MAVLink_sys_status_message(0, 0, 0, 500, 16000, 1000, 80, 0, 0, 0, 0, 0, 0))

    def _answer(self, msg: Any) -> None:
        if not self.identified.is_set():
            self.uplink_before_heartbeat.append(msg.get_type())
        super()._answer(msg)


def test_an_airframe_is_tasked_with_the_modes_its_heartbeat_names_not_before_it(
    tmp_path: Path,
) -> None:
    """An order waiting for an ArduPlane (no ``autopilot`` in the config; the processor's
    fallback is PX4): its position and battery state come first, and the order waits on
    until its HEARTBEAT; then it is started with ArduPlane's AUTO (10), never PX4's numbers,
    which an ArduPilot refuses."""
    link = free_udp_port()
    sock = tmp_path / "orders.sock"
    with running(write_config(tmp_path, link, sock)) as daemon:
        wait_until(sock.exists, 10.0, "the socket")
        code, lines = order_cli(
            sock, "--task", "observe_point", "--point", "65.84", "21.01", "--airframe",
            "F26E-001", "--order-id", "IDENT-1",
        )  # fmt: skip
        assert code == 3, lines
        with SlowToIdentify(link) as airframe:
            wait_until(
                lambda: daemon.status()["airframes"][0].get("active_link") is not None,
                30.0,
                "the airframe linked",
            )
            # Heard, with a position and a battery state, for a while: nothing is sent yet.
            time.sleep(1.0)  # some five telemetry rounds pass; the order must still wait
            assert airframe.uplink == []
            airframe.identified.set()
            wait_until(
                lambda: any(m.get_type() == "COMMAND_LONG" for m in airframe.uplink),
                20.0,
                "the start command",
            )
        assert airframe.uplink_before_heartbeat == []
        starts = [m for m in airframe.uplink if m.get_type() == "COMMAND_LONG"]
        assert {(m.command, m.param1, m.param2) for m in starts} == {(176, 1.0, 10.0)}
