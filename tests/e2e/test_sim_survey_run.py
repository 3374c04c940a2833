"""A survey and a return home flown by ``fischer-gateway simulate``, as an operator runs them.

``fischer-gateway run`` (the ``orders`` processor, the ``local`` order source, a jsonl archive)
and ``fischer-gateway simulate --autopilot px4 --speed 10`` beside it. ``fischer-gateway
order`` tasks a ``recon_area`` over a square east of the airframe's orbit: the order completes,
and the positions the node archived while it executed sweep the area with the camera's swath
(the default 60° across, at the 100 m above home the airframe flies: a polygon order carries
no altitude). Then ``return_to_base``: the simulated PX4 heads home on AUTO.RTL, publishes its
home, circles it armed, and the order completes once it has held near home for
``home_hold_s``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from daemon_support import archive_events, free_udp_port, running, wait_until
from footprints import covered_fraction
from test_sim_orders_run import order_cli, simulator, telemetry

pytestmark = pytest.mark.timeout(150)

AREA = [(65.828, 21.700), (65.828, 21.711), (65.8325, 21.711), (65.8325, 21.700)]
HOME = (65.8252, 21.6886)
#: What the default 60° camera sees across from 100 m above home.
SWATH_M = 2 * 100.0 * math.tan(math.radians(30.0))


def write_config(tmp_path: Path, link: int, sock: Path) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, autopilot: px4, links: [{{uri: 'udp://127.0.0.1:{link}',
     security: unsecured, name: fleet}}]}}
sources:
  - {{name: operator, type: local, socket: '{sock}'}}
processors:
  - {{name: orders, type: orders, options: {{home_hold_s: 3}}}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive], kinds: [order_status, telemetry]}}
"""
    )
    return config, archive


def flown_while(events: list[dict[str, Any]], order_id: str) -> list[tuple[float, float]]:
    """The archived positions between the order's executing and completed statuses."""
    marks = [
        i
        for i, e in enumerate(events)
        if e["kind"] == "order_status"
        and e["order_id"] == order_id
        and e["status"] in ("executing", "completed")
    ]
    start, end = marks[0], marks[-1]
    return [
        (e["position"]["lat_deg"], e["position"]["lon_deg"])
        for e in events[start:end]
        if e["kind"] == "telemetry" and e["position"]
    ]


def test_a_survey_covers_its_area_and_the_airframe_comes_home(tmp_path: Path) -> None:
    link = free_udp_port()
    sock = tmp_path / "orders.sock"
    config, archive = write_config(tmp_path, link, sock)
    with running(config), simulator(link, "px4"):
        wait_until(
            lambda: any(e["endurance_remaining_min"] for e in telemetry(archive)),
            30.0,
            "the simulated airframe's telemetry",
        )
        corners = [f"{lat},{lon}" for lat, lon in AREA]
        code, lines, stderr = order_cli(
            sock, "--task", "recon_area", "--airframe", "F26E-001", "--order-id", "SURVEY",
            "--polygon", *corners, "--follow", "--timeout", "100",
        )  # fmt: skip
        assert code == 0, stderr
        assert [line["status"] for line in lines] == [
            "received", "accepted", "executing", "completed"
        ]  # fmt: skip
        code, lines, stderr = order_cli(
            sock, "--task", "return_to_base", "--airframe", "F26E-001", "--order-id", "HOME",
            "--point", str(HOME[0]), str(HOME[1]), "--follow", "--timeout", "100",
        )  # fmt: skip
        assert code == 0, stderr
        assert [line["status"] for line in lines][-1] == "completed"
        assert lines[-1]["reason"].startswith("home reached: within 350 m of it")
        wait_until(
            lambda: sum(e.get("status") == "completed" for e in archive_events(archive)) == 2,
            10.0,
            "both completions archived",
        )
    events = archive_events(archive)
    swept = flown_while(events, "SURVEY")
    assert len(swept) > 50
    # The flown track, each position seeing a swath across: the area is covered. (The
    # planned footprints' ≥ 95 % is tests/e2e/test_orders_run.py's; a flown track cuts its
    # turns short of the planned corners.)
    assert covered_fraction(AREA, swept, SWATH_M) >= 0.9
