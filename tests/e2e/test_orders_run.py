"""Orders to the airframe in the daemon as operators run it, answered by MAVSDK.

``fischer-gateway run --config FILE`` in a child process with one airframe on an unsecured
loopback UDP link (MAVSDK speaks neither the tunnel nor signing; the test config says
``security: unsecured``), the ``orders`` processor with a geofence, an ``.hgt`` DEM tile with
a hill, an ``slb`` order source polling a real HTTPS SLB (``SlbPeer``) and a jsonl archive.
The airframe is ``MavsdkAutopilot``: MAVSDK's own autopilot-side command, mission and
telemetry servers, behind a relay that records what the gateway uplinks.

Orders out of endurance, outside the fence and below the terrain floor must be answered
``rejected`` at SLB with the check and its numbers while nothing at all goes to the airframe;
then an area reconnaissance order must go accepted → mission uploaded and acknowledged →
executing → completed, each state a receipt at SLB. With the airframe's COMMAND_ACKs lost,
the start command is retried and the order reported ``failed`` after the configured attempts.
"""

from __future__ import annotations

import json
import math
import socket
import stat
import subprocess
import sys
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from daemon_support import Airframe, archive_events, free_udp_port, running, wait_until
from footprints import covered_fraction
from mavsdk_autopilot import MavsdkAutopilot
from slb_peer import SlbPeer
from sweccis_peer import NS, SweccisPeer, order_document

from gateway.fleet.dialect import fischer_detection

pytestmark = pytest.mark.timeout(120)

ISSUED = "2026-11-22T12:00:00Z"
FENCE = [(65.0, 20.0), (65.0, 24.0), (67.0, 24.0), (67.0, 20.0)]
AREA = [(65.84, 21.02), (65.84, 21.06), (65.86, 21.06), (65.86, 21.02)]


def order(order_id: str, location: dict[str, Any], task: str = "observe_point") -> dict[str, Any]:
    return {
        "order_id": order_id,
        "issuer": "NB S3",
        "issued": ISSUED,
        "airframe": "F26E-001",
        "task": task,
        "location": location,
        "priority": "immediate",
    }


def point(lat: float, lon: float) -> dict[str, Any]:
    return {"point": {"lat_deg": lat, "lon_deg": lon}}


def write_dem(directory: Path) -> Path:
    """Flat ground at 100 m with a 650 m hill at 65.90-65.95 N, 21.40-21.45 E."""
    directory.mkdir()
    grid = np.full((1201, 1201), 100, dtype=">i2")
    grid[60:121, 480:541] = 650  # rows from 66° N down, columns from 21° E, 3″ apart
    (directory / "N65E021.hgt").write_bytes(grid.tobytes())
    return directory


def slb_source(peer: SlbPeer) -> str:
    tls = peer.tls_options()
    return f"""
  - name: brigade-slb
    type: slb
    base_url: '{peer.base_url}'
    ca_file: '{tls["ca_file"]}'
    cert_file: '{tls["cert_file"]}'
    key_file: '{tls["key_file"]}'
    poll_interval_s: 0.2"""


def sweccis_source(peer: SweccisPeer) -> str:
    tls = peer.link_options()
    return f"""
  - {{name: brigade-orders, type: sweccis, client_id: node-orders, reconnect_initial_s: 0.2,
     uri: '{tls["uri"]}', ca_file: '{tls["ca_file"]}', cert_file: '{tls["cert_file"]}',
     key_file: '{tls["key_file"]}'}}"""


def write_config(
    tmp_path: Path, source: str, link: int, *, sensor_link: int | None = None, **orders: Any
) -> tuple[Path, Path]:
    """The node's config; with ``sensor_link``, a second airframe (F2, sysid 2) that reports
    detections there, and the ``fusion`` processor making tracks of them."""
    archive = tmp_path / "archive.jsonl"
    sensor = fusion = ""
    if sensor_link is not None:
        sensor = f"""
  - {{id: F2, sysid: 2, links: [{{uri: 'udp://127.0.0.1:{sensor_link}', security: unsecured,
     name: sensor}}]}}"""
        fusion = """
  - {name: fusion, type: fusion, options: {lost_after_s: 2, update_interval_s: 0.2,
     tick_s: 0.1}}"""
    dem = write_dem(tmp_path / "dem")
    fence = ", ".join(f"{{lat_deg: {lat}, lon_deg: {lon}}}" for lat, lon in FENCE)
    extra = "".join(f", {key}: {value}" for key, value in orders.items())
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
terrain:
  sources: [{{name: srtm, kind: hgt, directory: '{dem}', sigma_m: 5.0}}]
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}{sensor}
sources:{source}
processors:{fusion}
  - name: orders
    type: orders
    options: {{geofence: [{fence}], time_on_task_s: 5{extra}}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive], kinds: [order, order_status, telemetry, track]}}
"""
    )
    return config, archive


def statuses(peer: SlbPeer, order_id: str) -> list[str]:
    return [r["status"] for r in peer.receipts_for(order_id)]


def ready(archive: Path) -> bool:
    """The airframe's telemetry has a position and a predicted endurance."""
    return any(
        e["kind"] == "telemetry" and e["position"] and e["endurance_remaining_min"]
        for e in archive_events(archive)
    )


def linked(daemon: Any) -> bool:
    """F26E-001 (the MAVSDK airframe) has an active link."""
    airframes = daemon.status()["airframes"]
    (airframe,) = [a for a in airframes if a["airframe"] == "F26E-001"]
    return airframe.get("active_link") is not None


@pytest.fixture(scope="module")
def tasked(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[SlbPeer, MavsdkAutopilot, list[str], list[dict[str, Any]]]:
    tmp_path = tmp_path_factory.mktemp("orders")
    link = free_udp_port()
    with SlbPeer(tmp_path / "pki").in_thread() as peer:
        config, archive = write_config(tmp_path, slb_source(peer), link)
        with running(config) as daemon, MavsdkAutopilot(link).running() as airframe:
            wait_until(lambda: linked(daemon), 30.0, "the MAVSDK airframe linked")
            wait_until(lambda: ready(archive), 20.0, "telemetry with endurance")
            peer.queue_order(order("FAR", point(66.95, 23.95)))
            peer.queue_order(order("OUT", point(64.50, 21.00)))
            peer.queue_order(order("HILL", point(65.925, 21.425)))
            for order_id in ("FAR", "OUT", "HILL"):
                wait_until(
                    lambda o=order_id: "rejected" in statuses(peer, o), 20.0, f"{order_id} rejected"
                )
            before = list(airframe.uplink)
            peer.queue_order(
                order(
                    "AREA",
                    {"polygon": [{"lat_deg": a, "lon_deg": b} for a, b in AREA]},
                    task="recon_area",
                )
            )
            wait_until(lambda: "completed" in statuses(peer, "AREA"), 30.0, "AREA completed")
        return peer, airframe, before, archive_events(archive)


def test_rejected_orders_name_the_check_and_send_nothing(
    tasked: tuple[SlbPeer, MavsdkAutopilot, list[str], list[dict[str, Any]]],
) -> None:
    peer, _, before, _ = tasked
    reasons = {o: peer.receipts_for(o)[-1]["reason"] for o in ("FAR", "OUT", "HILL")}
    for order_id in ("FAR", "OUT", "HILL"):
        assert statuses(peer, order_id) == ["received", "rejected"]
    assert reasons["FAR"].startswith("endurance: needs ")
    assert "has " in reasons["FAR"]
    assert reasons["OUT"].startswith("geofence: the route leaves the geofence at 64.50000")
    assert reasons["HILL"].startswith("terrain: commanded 500.0 m MSL is below the floor")
    assert "ground 650.0 m" in reasons["HILL"]
    # Nothing reached MAVSDK: no mission, no command, no frame at all from the gateway.
    assert not {"MISSION_COUNT", "MISSION_ITEM_INT", "COMMAND_LONG"} & set(before)
    assert before == []


def test_area_order_round_trips_through_mavsdk(
    tasked: tuple[SlbPeer, MavsdkAutopilot, list[str], list[dict[str, Any]]],
) -> None:
    peer, airframe, _, events = tasked
    assert statuses(peer, "AREA") == ["received", "accepted", "executing", "completed"]
    # Each status receipt carries its seq, for SLB to drop one sent again after a restart.
    assert [r["seq"] for r in peer.receipts_for("AREA")] == [None, 1, 2, 3]
    # MAVSDK's mission server took a lawnmower over the area: two turn points per line.
    (mission,) = airframe.missions
    assert len(mission) >= 8
    assert len(mission) % 2 == 0
    assert [item[1] for item in mission] == [16] * len(mission)
    assert all(item[4] == pytest.approx(500.0) for item in mission)
    # The camera (60° across, the default) 400 m above the DEM's 100 m ground sees a swath
    # 2 · 400 · tan 30° wide: the union of its footprints along the uploaded legs covers the
    # ordered area (computed on geographiclib's plane by tests/footprints.py).
    swath = 2 * 400.0 * math.tan(math.radians(30.0))
    points = [(lat, lon) for _, _, lat, lon, _ in mission]
    assert covered_fraction(AREA, points, swath) >= 0.95
    assert airframe.flight_modes == ["MISSION"]
    assert airframe.items_completed == len(mission)
    assert airframe.flown == points  # it was there: completion needed it
    assert airframe.uplink.count("MISSION_COUNT") == 1
    archived = [e for e in events if e["kind"] == "order_status"]
    area = [e for e in archived if e["order_id"] == "AREA"]
    assert [e["status"] for e in area] == ["accepted", "executing", "completed"]
    assert area[-1]["mission_items"] == len(mission)
    receipt = peer.receipts_for("AREA")[-1]
    assert receipt["event_id"] == "slb-order-AREA-completed"


def window_ending_in(seconds: float) -> str:
    return (datetime.now(UTC) + timedelta(seconds=seconds)).isoformat().replace("+00:00", "Z")


@pytest.fixture(scope="module")
def before_heard(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[SlbPeer, MavsdkAutopilot, list[str]]:
    """Orders offered while the airframe is not heard yet; then it comes up."""
    tmp_path = tmp_path_factory.mktemp("orders-wait")
    link = free_udp_port()
    with SlbPeer(tmp_path / "pki").in_thread() as peer:
        config, _ = write_config(tmp_path, slb_source(peer), link)
        with running(config) as daemon:
            # SHORT's window ends while the airframe is unheard; LATE's lasts (bounded by the
            # test's own timeout, not asserted as a time).
            peer.queue_order(
                {**order("SHORT", point(65.85, 21.10)), "not_after": window_ending_in(5)}
            )
            late = {**order("LATE", point(65.85, 21.10)), "not_after": window_ending_in(600)}
            peer.queue_order(late)
            wait_until(lambda: "rejected" in statuses(peer, "SHORT"), 30.0, "SHORT rejected")
            assert "waiting" in statuses(peer, "LATE")
            assert not linked(daemon)
            # LATE again with another point: a conflict, the first LATE stands.
            peer.queue_order({**late, "location": point(65.86, 21.12)})
            wait_until(lambda: "conflict" in statuses(peer, "LATE"), 30.0, "LATE conflict")
            with MavsdkAutopilot(link).running() as airframe:
                wait_until(lambda: "completed" in statuses(peer, "LATE"), 60.0, "LATE completed")
            uplink = list(airframe.uplink)
        return peer, airframe, uplink


def test_an_order_offered_before_the_airframe_is_heard_is_flown_once_it_is(
    before_heard: tuple[SlbPeer, MavsdkAutopilot, list[str]],
) -> None:
    peer, airframe, _ = before_heard
    assert statuses(peer, "LATE") == [
        "received",
        "waiting",
        "conflict",
        "accepted",
        "executing",
        "completed",
    ]
    waiting = peer.receipts_for("LATE")[1]
    assert waiting["reason"].startswith("link: F26E-001 has no active link; waiting for it until")
    conflict = peer.receipts_for("LATE")[2]
    assert conflict["reason"].startswith("order_id: LATE was already taken with other content")
    # The first LATE was flown: MAVSDK's mission is the waypoint and loiter at its point.
    (mission,) = airframe.missions
    assert [(round(lat, 5), round(lon, 5)) for _, _, lat, lon, _ in mission] == [
        (65.85, 21.10),
        (65.85, 21.10),
    ]


def test_an_order_whose_window_ends_unheard_is_rejected_naming_the_check(
    before_heard: tuple[SlbPeer, MavsdkAutopilot, list[str]],
) -> None:
    peer, _, _ = before_heard
    assert statuses(peer, "SHORT") == ["received", "waiting", "rejected"]
    reason = peer.receipts_for("SHORT")[-1]["reason"]
    assert reason.startswith("link: F26E-001 has no active link; waited ")
    assert ", until the window's end at " in reason


TARGET = (65.85, 21.10)


def detection_at(sensor: Airframe, north_m: float) -> bytes:
    """F2's EO detection of a vehicle ``north_m`` north of TARGET."""
    sensor.detections += 1
    message = fischer_detection(
        time_usec=round(time.time() * 1e6),
        detection_id=sensor.detections,
        lat_e7=round((TARGET[0] + north_m / 111_320.0) * 1e7),
        lon_e7=round(TARGET[1] * 1e7),
        alt_msl_m=100.0,
        sigma_h_m=8.0,
        class_id=1,
        sensor=0,
        confidence_pct=90,
        subtype="T-72",
    )
    return bytes(message.pack(sensor.mav))


def tracks(archive: Path) -> list[dict[str, Any]]:
    return [e for e in archive_events(archive) if e["kind"] == "track"]


@pytest.fixture(scope="module")
def followed(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[SlbPeer, MavsdkAutopilot, list[dict[str, Any]]]:
    """A track_target order on a fused track that moves north, then is lost."""
    tmp_path = tmp_path_factory.mktemp("orders-track")
    link, sensor_link = free_udp_port(), free_udp_port()
    sensor = Airframe(2)
    with SlbPeer(tmp_path / "pki").in_thread() as peer:
        config, archive = write_config(
            tmp_path,
            slb_source(peer),
            link,
            sensor_link=sensor_link,
            track_replan_s=0.5,
            track_replan_m=50,
        )
        with (
            running(config) as daemon,
            MavsdkAutopilot(link).running() as airframe,
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as radio,
        ):
            wait_until(lambda: linked(daemon), 30.0, "the MAVSDK airframe linked")
            wait_until(lambda: ready(archive), 20.0, "telemetry with endurance")
            radio.sendto(sensor.heartbeat(), ("127.0.0.1", sensor_link))
            for _ in range(3):  # confirmed after three detections
                radio.sendto(detection_at(sensor, 0.0), ("127.0.0.1", sensor_link))
                time.sleep(0.05)
            wait_until(lambda: bool(tracks(archive)), 15.0, "the track created")
            track_id = tracks(archive)[0]["track_id"]
            peer.queue_order(
                {**order("FOLLOW", point(*TARGET), task="track_target"), "track_id": track_id}
            )
            wait_until(lambda: "executing" in statuses(peer, "FOLLOW"), 30.0, "FOLLOW executing")
            north = 0.0
            while len(airframe.missions) < 2:  # the vehicle drives north, 5 m a step
                north += 5.0
                radio.sendto(detection_at(sensor, north), ("127.0.0.1", sensor_link))
                time.sleep(0.1)
                assert north < 5000, "the orbit never moved"
            # The reports stop: the track is lost, and with it the order is done.
            wait_until(lambda: "completed" in statuses(peer, "FOLLOW"), 30.0, "FOLLOW completed")
        return peer, airframe, tracks(archive)


def test_track_target_follows_the_fused_track_until_it_is_lost(
    followed: tuple[SlbPeer, MavsdkAutopilot, list[dict[str, Any]]],
) -> None:
    peer, airframe, events = followed
    assert statuses(peer, "FOLLOW") == ["received", "accepted", "executing", "completed"]
    track_id = events[0]["track_id"]
    assert peer.receipts_for("FOLLOW")[-1]["reason"] == f"track {track_id} was lost"
    first, moved = airframe.missions[0], airframe.missions[1]
    # Each orbit is a waypoint and a timed loiter at the track's position then.
    assert [item[1] for item in first] == [16, 19]
    assert [item[1] for item in moved] == [16, 19]
    assert (first[1][2], first[1][3]) == pytest.approx(TARGET, abs=2e-4)
    moved_to = (moved[1][2], moved[1][3])
    seen = [
        (e["position"]["lat_deg"], e["position"]["lon_deg"])
        for e in events
        if e["track_id"] == track_id
    ]
    assert moved_to in [pytest.approx(p, abs=1e-6) for p in seen]  # a position the track reported
    assert moved_to[0] > TARGET[0] + 50 / 111_320.0 * 0.9  # moved north, past track_replan_m
    assert any(e["status"] == "lost" for e in events)


@pytest.fixture(scope="module")
def unacknowledged(tmp_path_factory: pytest.TempPathFactory) -> tuple[SlbPeer, MavsdkAutopilot]:
    tmp_path = tmp_path_factory.mktemp("orders-ack")
    link = free_udp_port()
    with SlbPeer(tmp_path / "pki").in_thread() as peer:
        config, archive = write_config(
            tmp_path, slb_source(peer), link, command_timeout_s=0.5, command_retries=2
        )
        autopilot = MavsdkAutopilot(link, drop_command_acks=True)
        with running(config) as daemon, autopilot.running() as airframe:
            wait_until(lambda: linked(daemon), 30.0, "the MAVSDK airframe linked")
            wait_until(lambda: ready(archive), 20.0, "telemetry with endurance")
            peer.queue_order(order("NOACK", point(65.85, 21.10)))
            wait_until(lambda: "failed" in statuses(peer, "NOACK"), 30.0, "NOACK failed")
        return peer, airframe


def test_lost_command_ack_is_retried_then_failed(
    unacknowledged: tuple[SlbPeer, MavsdkAutopilot],
) -> None:
    peer, airframe = unacknowledged
    assert statuses(peer, "NOACK") == ["received", "accepted", "failed"]
    reason = peer.receipts_for("NOACK")[-1]["reason"]
    assert reason == "command: no COMMAND_ACK for command 176 after 3 attempts"
    assert airframe.uplink.count("COMMAND_LONG") == 3  # the first and two retries
    assert airframe.dropped_acks >= 3  # MAVSDK answered each; the link lost them
    assert len(airframe.missions) == 1  # the mission itself was uploaded and acknowledged


@pytest.fixture(scope="module")
def over_sweccis(tmp_path_factory: pytest.TempPathFactory) -> SweccisPeer:
    tmp_path = tmp_path_factory.mktemp("orders-sweccis")
    link = free_udp_port()
    with SweccisPeer(tmp_path / "pki").in_thread() as peer:
        config, archive = write_config(tmp_path, sweccis_source(peer), link)
        with running(config) as daemon, MavsdkAutopilot(link).running():
            wait_until(lambda: linked(daemon), 30.0, "the MAVSDK airframe linked")
            wait_until(lambda: ready(archive), 20.0, "telemetry with endurance")
            outside = order_document("doc-out", "SW-OUT", airframe="F26E-001", point=(64.5, 21.0))
            inside = order_document("doc-in", "SW-IN", airframe="F26E-001", point=(65.85, 21.1))
            peer.call(peer.push_order, outside)
            peer.call(peer.push_order, inside)
            wait_until(
                lambda: (
                    "completed" in peer.order_statuses("SW-IN")
                    and "rejected" in peer.order_statuses("SW-OUT")
                ),
                30.0,
                "SWECCIS told of both orders",
            )
        return peer


def test_sweccis_gets_each_status_as_an_order_status_document(over_sweccis: SweccisPeer) -> None:
    peer = over_sweccis
    assert peer.invalid == []  # every OrderStatus document passed the shipped XSD
    assert [(ref, status) for ref, status, _ in peer.order_acks] == [
        ("doc-out", "accepted"),
        ("doc-in", "accepted"),
    ]
    assert peer.order_statuses("SW-OUT") == ["rejected"]
    assert peer.order_statuses("SW-IN") == ["accepted", "executing", "completed"]
    (rejected,) = [d for d in peer.of("OrderStatus") if d.findtext(f"{NS}OrderId") == "SW-OUT"]
    assert rejected.findtext(f"{NS}Check") == "geofence"
    assert rejected.findtext(f"{NS}Reason", "").startswith("the route leaves the geofence at 64.5")
    assert rejected.get("id") == "sweccis-order-SW-OUT-rejected"


def order_cli(sock: Path, *args: str) -> tuple[int, list[dict[str, Any]], str]:
    command = [sys.executable, "-m", "gateway", "order", "--socket", str(sock), *args]
    done = subprocess.run(command, capture_output=True, timeout=60, check=False)
    lines = [json.loads(line) for line in done.stdout.decode().splitlines() if line.strip()]
    return done.returncode, lines, done.stderr.decode(errors="replace")


@pytest.fixture(scope="module")
def by_operator(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[Path, dict[str, tuple[int, list[dict[str, Any]], str]], bytes, int]:
    tmp_path = tmp_path_factory.mktemp("orders-local")
    link = free_udp_port()
    sock = tmp_path / "orders.sock"
    source = f"\n  - {{name: operator, type: local, socket: '{sock}'}}"
    config, archive = write_config(tmp_path, source, link)
    runs = {}
    with running(config) as daemon, MavsdkAutopilot(link).running():
        wait_until(lambda: linked(daemon), 30.0, "the MAVSDK airframe linked")
        wait_until(lambda: ready(archive), 20.0, "telemetry with endurance")
        mode = stat.S_IMODE(sock.stat().st_mode)
        common = ("--task", "observe_point", "--airframe", "F26E-001", "--follow")
        runs["in"] = order_cli(sock, *common, "--order-id", "OP-1", "--point", "65.85", "21.10")
        runs["out"] = order_cli(sock, *common, "--order-id", "OP-2", "--point", "64.5", "21.0")
        area = ("--task", "recon_area", "--airframe", "F26E-001", "--follow")
        # The red team's 170 km leg along the fence's 65 N edge, 89 m north of the parallel
        # (inside in latitude and longitude), and one 445 m north whose ends and geodesic are
        # inside the geodesic edge but whose rhumb line (how ArduPilot flies it) is not.
        edge = ("--polygon", "65.0008,20.2", "65.0008,23.8", "65.3,23.8", "65.3,20.2")
        runs["edge"] = order_cli(sock, *area, "--order-id", "OP-3", *edge)
        rhumb = ("--polygon", "65.004,20.1", "65.004,23.9", "65.3,23.9", "65.3,20.1")
        runs["rhumb"] = order_cli(sock, *area, "--order-id", "OP-4", *rhumb)
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as raw:
            raw.settimeout(10)
            raw.connect(str(sock))
            raw.sendall(b"{not json\n")
            garbage = raw.makefile("rb").readline()
    return sock, runs, garbage, mode


def test_an_operator_order_from_the_command_line_runs_to_completed(
    by_operator: tuple[Path, dict[str, tuple[int, list[dict[str, Any]], str]], bytes, int],
) -> None:
    _, runs, _, mode = by_operator
    code, lines, stderr = runs["in"]
    assert code == 0, stderr
    assert [line["status"] for line in lines] == ["received", "accepted", "executing", "completed"]
    assert lines[0]["event_id"] == "local-order-OP-1"
    assert {line["airframe"] for line in lines[1:]} == {"F26E-001"}
    assert mode == 0o600  # only the daemon's user (and root) may task the fleet


def test_an_operator_order_outside_the_fence_is_rejected_with_its_reason(
    by_operator: tuple[Path, dict[str, tuple[int, list[dict[str, Any]], str]], bytes, int],
) -> None:
    _, runs, garbage, _ = by_operator
    code, lines, _ = runs["out"]
    assert code == 1
    assert [line["status"] for line in lines] == ["received", "rejected"]
    assert lines[-1]["check"] == "geofence"
    assert lines[-1]["reason"].startswith("the route leaves the geofence at 64.5")
    assert json.loads(garbage) == {"status": "rejected", "reason": "order: not JSON"}


def test_a_leg_along_the_fence_edge_is_checked_on_the_ellipsoid(
    by_operator: tuple[Path, dict[str, tuple[int, list[dict[str, Any]], str]], bytes, int],
) -> None:
    """The fence's edges are geodesics, and a leg is checked as PX4 and ArduPilot fly it."""
    _, runs, _, _ = by_operator
    for name in ("edge", "rhumb"):
        code, lines, _ = runs[name]
        assert code == 1
        assert [line["status"] for line in lines] == ["received", "rejected"]
        assert lines[-1]["check"] == "geofence"
    # The survey's first line runs along the area's 65 N edge, half a line spacing inside
    # it (65.00244 N, 65.00564 N): still outside the geodesic edge, and the second still
    # outside only as the rhumb line it is flown as.
    assert runs["edge"][1][-1]["reason"] == (
        "the route leaves the geofence at 65.00244, 20.20000 (lat, lon), 11 m outside"
    )
    assert runs["rhumb"][1][-1]["reason"] == (
        "the route leaves the geofence at 65.00564, 22.00000 (lat, lon), 863 m outside,"
        " on the leg 65.00564, 20.10000 to 65.00564, 23.90000 flown as the rhumb line"
    )
