"""An operator's order flown by the simulator, as an operator runs both: two processes.

``fischer-gateway run --config FILE`` (one airframe on a loopback UDP link, the ``orders``
processor, the ``local`` order source and a jsonl archive) and ``fischer-gateway simulate
--airframes 1 --autopilot px4|ardupilot --speed 10`` beside it. ``fischer-gateway order``
tasks the airframe to observe a point 2.6 km from its orbit at a new altitude: the order must
go received → accepted → executing → completed, and the positions the gateway archived must
follow the mission the processor planned (a waypoint at the point, then a timed loiter on a
circle around it): along the leg, through the waypoint's acceptance radius, then on the
circle, climbing to the commanded altitude. The PX4 airframe is named ``autopilot: px4`` in
the config; the ArduPilot one is recognised from its HEARTBEAT (the processor's own default
is PX4), and its telemetry shows ArduPlane's AUTO and then, with the mission done, RTL.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from daemon_support import archive_events, free_udp_port, running, wait_until

from gateway.domain.geodesy import distance_bearing

pytestmark = pytest.mark.timeout(150)

POINT = (65.8400, 21.7400)
ALT_MSL_M = 320.0
LOITER_RADIUS_M = 250.0
TIME_ON_TASK_S = 20.0  # sim seconds: 2 s at --speed 10
#: The node counts time on task on its own clock, the simulator on its sped-up one: ArduPlane
#: turns home (RTL) once its loiter is done, so its order asks only the time the node sees a
#: ten-times airframe spend near the point (a real airframe flies at speed 1).
ARDUPILOT_TIME_ON_TASK_S = 2.0
SPEED = 10.0
#: The simulated airframe's orbit (SimProfile's default centre and radius), where it starts.
ORBIT_CENTRE = (65.8252, 21.6886)
#: What the simulated airframe's tightest turn and its acceptance radius come to (22 m/s,
#: 35° of bank: 70 m), with room for a position sampled every 0.1 s of sim time.
ACCEPTANCE_M = 80.0 + 5.0
PX4_AUTO_MISSION = 4 << 16 | 4 << 24
ARDUPLANE_AUTO, ARDUPLANE_RTL = 10, 11


@dataclass
class Flown:
    statuses: list[str]
    lines: list[dict[str, Any]]
    positions: list[tuple[float, float, float]]  # lat, lon, alt MSL between executing and done
    modes: list[int]  # HEARTBEAT custom_mode, in order, from executing on
    start: tuple[float, float]
    items: int | None


def write_config(
    tmp_path: Path, link: int, sock: Path, extra: str, on_task_s: float
) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]{extra}}}
sources:
  - {{name: operator, type: local, socket: '{sock}'}}
processors:
  - name: orders
    type: orders
    options: {{time_on_task_s: {on_task_s}, loiter_radius_m: {LOITER_RADIUS_M}}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive], kinds: [order_status, telemetry]}}
"""
    )
    return config, archive


@contextmanager
def simulator(link: int, autopilot: str) -> Iterator[subprocess.Popen[bytes]]:
    """``fischer-gateway simulate``: one airframe (sysid 1), plain MAVLink, ten times real."""
    command = [
        sys.executable, "-m", "gateway", "simulate", "--to", f"udp://127.0.0.1:{link}",
        "--airframes", "1", "--autopilot", autopilot, "--speed", str(SPEED), "--no-resend",
    ]  # fmt: skip
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()


def order_cli(sock: Path, *args: str) -> tuple[int, list[dict[str, Any]], str]:
    command = [sys.executable, "-m", "gateway", "order", "--socket", str(sock), *args]
    done = subprocess.run(command, capture_output=True, timeout=120, check=False)
    lines = [json.loads(line) for line in done.stdout.decode().splitlines() if line.strip()]
    return done.returncode, lines, done.stderr.decode(errors="replace")


def telemetry(archive: Path) -> list[dict[str, Any]]:
    return [e for e in archive_events(archive) if e["kind"] == "telemetry" and e["position"]]


def fly(tmp_path: Path, autopilot: str, extra: str, on_task_s: float) -> Flown:
    link = free_udp_port()
    sock = tmp_path / "orders.sock"
    config, archive = write_config(tmp_path, link, sock, extra, on_task_s)
    with running(config), simulator(link, autopilot):
        # Its battery state and its HEARTBEAT (which names the autopilot: until then an
        # airframe not configured with one is not tasked, and the order would wait first).
        wait_until(
            lambda: (
                any(e["endurance_remaining_min"] for e in telemetry(archive))
                and any(e["autopilot"] is not None for e in telemetry(archive))
            ),
            30.0,
            "the simulated airframe's telemetry",
        )
        code, lines, stderr = order_cli(
            sock, "--task", "observe_point", "--airframe", "F26E-001", "--order-id", "SIM-1",
            "--point", str(POINT[0]), str(POINT[1]), "--alt-msl-m", str(ALT_MSL_M),
            "--follow", "--timeout", "90",
        )  # fmt: skip
        assert code == 0, stderr
        wait_until(
            lambda: any(e.get("status") == "completed" for e in archive_events(archive)),
            10.0,
            "the completed status archived",
        )
    events = archive_events(archive)
    statuses = [e for e in events if e["kind"] == "order_status"]
    executing = events.index(next(e for e in statuses if e["status"] == "executing"))
    completed = events.index(next(e for e in statuses if e["status"] == "completed"))
    before = [e for e in events[:executing] if e["kind"] == "telemetry" and e["position"]]
    during = [e for e in events[executing:completed] if e["kind"] == "telemetry" and e["position"]]
    after = [e for e in events[executing:] if e["kind"] == "telemetry"]
    last = before[-1]["position"]
    return Flown(
        statuses=[line["status"] for line in lines],
        lines=lines,
        positions=[
            (e["position"]["lat_deg"], e["position"]["lon_deg"], e["position"]["alt_msl_m"])
            for e in during
        ],
        modes=[e["custom_mode"] for e in after],
        start=(last["lat_deg"], last["lon_deg"]),
        items=next(e for e in statuses if e["status"] == "accepted")["mission_items"],
    )


def distance_m(a: tuple[float, float], b: tuple[float, float]) -> float:
    return float(distance_bearing(a[0], a[1], b[0], b[1])[0])


def cross_track_m(
    start: tuple[float, float], end: tuple[float, float], p: tuple[float, float]
) -> float:
    """How far ``p`` is from the great circle through ``start`` and ``end``."""
    d13, b13 = distance_bearing(start[0], start[1], p[0], p[1])
    _, b12 = distance_bearing(start[0], start[1], end[0], end[1])
    return (
        abs(math.asin(math.sin(d13 / 6_371_000.0) * math.sin(math.radians(b13 - b12))))
        * 6_371_000.0
    )


def check_flight(flown: Flown, *, round_the_circle: bool = True) -> None:
    """The archived positions follow the planned items: leg, waypoint, loiter circle."""
    assert flown.statuses == ["received", "accepted", "executing", "completed"]
    assert flown.items == 2  # the waypoint and the loiter
    points = [(lat, lon) for lat, lon, _ in flown.positions]
    assert len(points) > 50, "positions while the order executed"
    to_point = [distance_m(p, POINT) for p in points]
    arrived = next(i for i, d in enumerate(to_point) if d <= ACCEPTANCE_M)
    # The leg: from where the airframe was when the mission started, straight at the point
    # once it has turned off its orbit (a turn takes at most a 70 m-radius circle).
    assert distance_m(flown.start, ORBIT_CENTRE) == pytest.approx(400.0, abs=30.0)
    for p in points[:arrived]:
        assert cross_track_m(flown.start, POINT, p) <= 2 * 70.0 + 30.0
    # Through the waypoint, then out to the loiter circle and round it: never further out.
    assert all(d <= LOITER_RADIUS_M + 40.0 for d in to_point[arrived:])
    if round_the_circle:
        on_circle = [d for d in to_point[arrived:] if abs(d - LOITER_RADIUS_M) <= 25.0]
        # Time on task, on the circle: 20 s of sim time at 10 Hz, whatever the archive kept.
        assert len(on_circle) >= 10
        assert abs(to_point[-1] - LOITER_RADIUS_M) <= 25.0
    # Climbing at most 4 m/s from 250 m to the commanded 320 m, and holding it.
    assert flown.positions[-1][2] == pytest.approx(ALT_MSL_M, abs=0.5)
    assert all(250.0 - 0.5 <= alt <= ALT_MSL_M + 0.5 for _, _, alt in flown.positions)


@pytest.fixture(scope="module")
def px4(tmp_path_factory: pytest.TempPathFactory) -> Flown:
    return fly(tmp_path_factory.mktemp("sim-px4"), "px4", ", autopilot: px4", TIME_ON_TASK_S)


@pytest.fixture(scope="module")
def ardupilot(tmp_path_factory: pytest.TempPathFactory) -> Flown:
    return fly(tmp_path_factory.mktemp("sim-ardupilot"), "ardupilot", "", ARDUPILOT_TIME_ON_TASK_S)


def test_a_px4_airframe_flies_the_order_it_was_given(px4: Flown) -> None:
    check_flight(px4)
    assert PX4_AUTO_MISSION in px4.modes  # AUTO.MISSION, started by the PX4 custom mode


def test_an_ardupilot_airframe_heard_as_one_flies_the_order_in_auto(ardupilot: Flown) -> None:
    # Its short loiter (ArduPlane times it from the point) ends before it is out on the circle.
    check_flight(ardupilot, round_the_circle=False)
    # The gateway heard ArduPilot in the HEARTBEAT and asked for ArduPlane's AUTO (10) by
    # number; at the mission's end ArduPlane goes home on its own (RTL, 11).
    assert ARDUPLANE_AUTO in ardupilot.modes
    assert ardupilot.modes.index(ARDUPLANE_AUTO) < ardupilot.modes.index(ARDUPLANE_RTL)
