"""A stranger against the hop schedule of ``fischer-gateway run``, with plain MAVLink only.

On an unsecured link anyone on the network may speak as the airframe: it can answer the
upload and report hops. What it must not get is a lever beyond that link: an uplink flooded
with re-uploads, a log line per packet, or hop counts on /metrics that count the same hops
again and again. On a tunnel link it gets nothing at all: its answers and hop reports, on
the tunnel port or on another airframe's unsecured port, change nothing on /status.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from daemon_support import (
    Airframe,
    free_udp_port,
    running,
    sealer,
    three_airframe_node,
    wait_until,
)
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.fleet.hopdialect import FischerHopEvent, FischerHopSchedule, FischerHopScheduleAck

pytestmark = pytest.mark.timeout(90)

PLAN = (
    "{frequencies_mhz: [2405, 2430], bandwidth_mhz: 10, dwell_us: 12, "
    "ack_timeout_s: 0.2, retry_max_s: 1}"
)


def unsecured_node(tmp_path: Path, port: int) -> Path:
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - id: F26E-001
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{port}', security: unsecured, name: fleet}}]
    hop_plan: {PLAN}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{tmp_path / "archive.jsonl"}'}}}}
routes:
  - {{sinks: [archive], kinds: [hop]}}
"""
    )
    return config


def hop_event(sender: mav.MAVLink, schedule: int, hop_count: int, reason: int = 0) -> bytes:
    now_us = round(time.time() * 1e6)
    message = FischerHopEvent(now_us, 2_405_000_000, schedule, hop_count, 0, reason, -60, 127)
    return bytes(message.pack(sender))


def ack(sender: mav.MAVLink, schedule: int, active: int, result: int = 0) -> bytes:
    return bytes(FischerHopScheduleAck(schedule, active, 255, 191, result).pack(sender))


def schedules_in(data: bytes) -> list[int]:
    messages = mav.MAVLink(None).parse_buffer(data) or []
    return [int(m.schedule_id) for m in messages if m.get_type() == "FISCHER_HOP_SCHEDULE"]


def test_reports_of_another_schedule_cannot_loop_the_upload_or_the_log(
    tmp_path: Path, udp_socket: Callable[[], socket.socket]
) -> None:
    """Every upload answered ACCEPTED, and every hop report on another schedule: the gateway
    uploads again, but backs off (ack_timeout_s doubling up to retry_max_s) instead of
    re-uploading every ack_timeout_s for as long as the stranger likes."""
    port = free_udp_port()
    stranger = udp_socket()
    stranger.settimeout(0.02)
    me = Airframe(1).mav
    with running(unsecured_node(tmp_path, port)) as daemon:
        stranger.sendto(Airframe(1).heartbeat(), ("127.0.0.1", port))
        uploads: list[float] = []
        started = time.monotonic()
        while time.monotonic() - started < 6.0:
            stranger.sendto(hop_event(me, 0xDEADBEEF, 1), ("127.0.0.1", port))
            try:
                data = stranger.recv(4096)
            except TimeoutError:
                continue
            for schedule in schedules_in(data):
                uploads.append(time.monotonic() - started)
                stranger.sendto(ack(me, schedule, schedule), ("127.0.0.1", port))
        accepted_lines = len(daemon.events("hop_schedule_accepted"))
        lost_lines = len(daemon.events("hop_schedule_lost"))
        (upload,) = daemon.status()["hop_schedules"]
    # Without a backoff: one upload per ack_timeout_s (0.2 s), some 30 in 6 s. With it: the
    # waits go 0, 0.2, 0.4, 0.8, then 1 s, each after the 0.2 s grace: about 8.
    assert 3 <= len(uploads) <= 10, uploads
    assert accepted_lines <= 2
    assert lost_lines <= 1
    assert len(uploads) <= upload["sends"] <= len(uploads) + 1  # one may be on its way
    assert upload["active_schedule_id"] == "deadbeef"


def test_interleaved_reports_of_two_schedules_count_each_hop_once(
    tmp_path: Path, udp_socket: Callable[[], socket.socket]
) -> None:
    """Reports of the old and the new schedule arriving mixed (two links, reordering, or a
    stranger alternating them) add only the hops each schedule's counter moved on."""
    port = free_udp_port()
    airframe = udp_socket()
    me = Airframe(1).mav
    old, new = 0x1000, 0x2000
    reports = [(old, 1000), (new, 10), (old, 1000), (new, 20), (old, 1001), (new, 20)]
    reports += [(old if n % 2 else new, 2_000_000_000) for n in range(200)]
    with running(unsecured_node(tmp_path, port)) as daemon:
        for schedule, hop_count in reports:
            airframe.sendto(hop_event(me, schedule, hop_count), ("127.0.0.1", port))
        wait_until(
            lambda: daemon.metric("fg_hop_events_total", airframe="F26E-001") == len(reports),
            10,
            "every report counted",
        )
        flown = daemon.metric("fg_hops_total", airframe="F26E-001")
    # old: 1000, then 1001, then 2e9; new: 10, 20, then 2e9: each counter's last value.
    assert flown == 2_000_000_000 * 2


def test_a_stranger_without_keys_moves_nothing_of_a_tunnel_airframes_upload(
    tmp_path: Path, udp_socket: Callable[[], socket.socket]
) -> None:
    """Plain answers and hop reports as sysid 1, on the tunnel port and on the unsecured
    airframe's port: refused (auth, foreign_link), and /status tells the truth."""
    ports = {name: free_udp_port() for name in ("tun", "sig", "open")}
    tun_extra = f"    hop_plan: {PLAN}\n"
    config, archive = three_airframe_node(tmp_path, ports, tun_extra=tun_extra)
    genuine, stranger = udp_socket(), udp_socket()
    tun = Airframe(1)
    with running(config) as daemon:
        genuine.sendto(sealer("TUN").seal(tun.heartbeat()), ("127.0.0.1", ports["tun"]))
        wait_until(lambda: daemon.status()["hop_schedules"][0]["sends"] >= 1, 10, "an upload")
        schedule = int(daemon.status()["hop_schedules"][0]["schedule_id"], 16)
        for port in (ports["tun"], ports["open"], ports["sig"]):
            for _ in range(3):
                stranger.sendto(ack(tun.mav, schedule, schedule), ("127.0.0.1", port))
                stranger.sendto(hop_event(tun.mav, schedule, 7, 1), ("127.0.0.1", port))
        wait_until(
            lambda: daemon.metric("fg_link_frames_rejected_total", reason="foreign_link") >= 12,
            10,
            "the foreign frames refused",
        )
        (upload,) = daemon.status()["hop_schedules"]
        events = daemon.metric("fg_hop_events_total")
        answers = daemon.metric("fg_hop_schedule_answers_total")
    assert upload["state"] in ("sent", "waiting_link")
    assert (upload["last_result"], upload["active_schedule_id"]) == (None, None)
    assert (events, answers) == (0.0, 0.0)
    assert not archive.exists() or "hop" not in archive.read_text()


def test_a_local_process_cannot_upload_its_own_hop_schedule_through_the_passthrough(
    tmp_path: Path, udp_socket: Callable[[], socket.socket]
) -> None:
    """The passthrough takes plain MAVLink from any local process and seals it for the
    airframe. A FISCHER_HOP_SCHEDULE there would replace the checked plan with one that need
    not beat the jammer (and start a tug of war with the gateway's re-uploads): it is
    refused, whole, split across datagrams or hidden behind garbage; other frames still go."""
    ports = {name: free_udp_port() for name in ("tun", "sig", "open", "gcs")}
    tun_extra = (
        f"    hop_plan: {PLAN}\n"
        f"    passthrough: {{uri: 'udp://127.0.0.1:{ports['gcs']}', uplink: open}}\n"
    )
    config, _archive = three_airframe_node(tmp_path, ports, tun_extra=tun_extra)
    genuine, stranger = udp_socket(), udp_socket()
    tun = Airframe(1)
    gcs = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    slow = FischerHopSchedule(0, [2_405_000_000] + [0] * 7, 77, 10_000_000, 100_000, 0, 1, 0, 1)
    rogue = bytes(slow.pack(gcs))
    heartbeat = bytes(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs))
    with running(config) as daemon:
        seal = sealer("TUN")
        genuine.sendto(seal.seal(tun.heartbeat()), ("127.0.0.1", ports["tun"]))
        wait_until(lambda: daemon.status()["hop_schedules"][0]["sends"] >= 1, 10, "an upload")
        schedule = int(daemon.status()["hop_schedules"][0]["schedule_id"], 16)
        genuine.sendto(seal.seal(ack(tun.mav, schedule, schedule)), ("127.0.0.1", ports["tun"]))
        wait_until(
            lambda: daemon.status()["hop_schedules"][0]["state"] == "accepted", 10, "accepted"
        )
        for datagram in (rogue, b"\x00garbage\xfd" + rogue, rogue[:20], rogue[20:], heartbeat):
            stranger.sendto(datagram, ("127.0.0.1", ports["gcs"]))
        wait_until(
            lambda: daemon.status()["passthroughs"][0]["uplink_frames"] >= 1, 10, "the heartbeat"
        )
        (passthrough,) = daemon.status()["passthroughs"]
        sends = daemon.status()["hop_schedules"][0]["sends"]
        received = drain(genuine)
    # Refused: the whole frame as the gateway's own message; the frame behind garbage and
    # the two halves as not whole frames. Only re-serialised frames leave, so no bytes of
    # theirs reach the airframe for its parser to join.
    assert passthrough["refused"]["gateway_only"] == 1
    assert passthrough["refused"]["truncated"] == 2
    assert passthrough["refused"]["malformed"] == 2
    assert passthrough["uplink_frames"] == 1
    # What reached the airframe: the gateway's uploads and the heartbeat, re-serialised.
    assert len(received) == sends + 1


def drain(sock: socket.socket) -> list[bytes]:
    sock.settimeout(0.3)
    got = []
    while True:
        try:
            got.append(sock.recv(4096))
        except TimeoutError:
            return got
