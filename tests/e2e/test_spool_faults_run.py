"""A spool that cannot commit, and one damaged while the gateway was down, through ``run``.

``fischer-gateway run`` in a child process with a spool file, one unsecured airframe on
loopback UDP and a ``null`` sink; detections are pymavlink frames from a test socket.

1. The file-size limit of the running daemon is lowered to what its WAL holds
   (``prlimit`` RLIMIT_FSIZE: writes past it fail with EFBIG, for root too; Python ignores
   SIGXFSZ): the next detection is not acknowledged, and /metrics, /status and /readyz say
   why; once the limit is lifted the airframe's re-send is taken and acknowledged, and after
   a SIGKILL the next start counts no loss.
2. The gateway killed with SIGKILL, a byte of its WAL damaged: the next start says at error,
   on /status and on /metrics how many frames and commits SQLite could not replay, and keeps
   a copy of the log.
3. The database itself damaged: moved aside, the gateway starts on an empty spool and says so.
"""

from __future__ import annotations

import resource
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest
from daemon_support import Airframe, Daemon, free_udp_port, running, wait_until

pytestmark = pytest.mark.timeout(90)

FRAME = 24 + 4096


def write_node(tmp_path: Path, port: int) -> Path:
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
spool: {{path: '{tmp_path / "spool.db"}'}}
airframes:
  - id: OPEN
    sysid: 3
    links: [{{uri: 'udp://127.0.0.1:{port}', security: unsecured, name: open}}]
sinks:
  - {{name: void, type: 'null'}}
routes:
  - {{sinks: [void], kinds: [detection]}}
"""
    )
    return config


@pytest.fixture
def airframe_socket() -> Iterator[socket.socket]:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        yield sock


def held(daemon: Daemon) -> float:
    return daemon.metric("fg_detections_acknowledged_total", airframe="OPEN", result="held")


def send_detections(
    daemon: Daemon, sock: socket.socket, airframe: Airframe, port: int, count: int
) -> None:
    """``count`` detections, one datagram each, each acknowledged before the next."""
    for _ in range(count):
        before = held(daemon)
        sock.sendto(airframe.heartbeat() + airframe.detection(), ("127.0.0.1", port))
        wait_until(lambda: held(daemon) > before, 10, "the acknowledgement")  # noqa: B023


def test_a_failed_commit_is_counted_shown_and_acknowledges_nothing(
    tmp_path: Path, airframe_socket: socket.socket
) -> None:
    port = free_udp_port()
    config = write_node(tmp_path, port)
    airframe = Airframe(3)
    wal = tmp_path / "spool.db-wal"
    daemon = Daemon(config)
    try:
        send_detections(daemon, airframe_socket, airframe, port, 1)
        wait_until(lambda: daemon.get("/readyz")[0] == 200, 10, "ready")
        assert daemon.metric("fg_spool_commit_failures_total") == 0
        _, hard = resource.prlimit(daemon.proc.pid, resource.RLIMIT_FSIZE)
        resource.prlimit(daemon.proc.pid, resource.RLIMIT_FSIZE, (wal.stat().st_size, hard))
        again = airframe.heartbeat() + airframe.detection()
        airframe_socket.sendto(again, ("127.0.0.1", port))
        wait_until(
            lambda: daemon.metric("fg_spool_commit_failures_total", reason="io") >= 1,
            10,
            "the failed commit on /metrics",
        )
        spool = daemon.status()["spool"]
        assert spool["state"] == "failing"
        assert spool["reason"].startswith("writes fail to commit (io: disk I/O error)")
        assert spool["commits"]["failing"] is True
        assert spool["commits"]["last_failure"]["reason"] == "io"
        assert daemon.get("/readyz")[0] == 503
        assert daemon.metric("fg_ready") == 0
        assert held(daemon) == 1  # the detection that did not commit is not acknowledged
        (logged, *_) = daemon.events("spool_commit_failed")
        assert logged["level"] == "error"
        assert logged["reason"] == "io"
        # The disk is freed; the airframe sends the detection again and it is taken.
        resource.prlimit(daemon.proc.pid, resource.RLIMIT_FSIZE, (hard, hard))
        airframe_socket.sendto(again, ("127.0.0.1", port))
        wait_until(lambda: held(daemon) == 2, 10, "the re-sent detection acknowledged")
        spool = daemon.status()["spool"]
        assert (spool["state"], spool["reason"]) == ("ok", "")
        assert daemon.get("/readyz")[0] == 200
        assert daemon.events("spool_commits_recovered")
    finally:
        daemon.kill9()
    # What the failed commit wrote to the log before it failed never committed: after a
    # crash, the next start counts no loss.
    with running(config) as restarted:
        start = restarted.status()["spool"]["start_check"]
    assert start["wal_frames"] > 0
    assert (start["wal_lost_frames"], start["wal_lost_commits"]) == (0, 0)
    assert not restarted.events("spool_wal_frames_lost")


def test_a_damaged_wal_at_start_is_reported_with_counts_and_kept(
    tmp_path: Path, airframe_socket: socket.socket
) -> None:
    port = free_udp_port()
    config = write_node(tmp_path, port)
    airframe = Airframe(3)
    first = Daemon(config)
    try:
        send_detections(first, airframe_socket, airframe, port, 20)
    finally:
        first.kill9()
    wal = tmp_path / "spool.db-wal"
    frames = (wal.stat().st_size - 32) // FRAME
    with wal.open("r+b") as handle:  # one byte in the page of the middle frame
        handle.seek(32 + (frames // 2) * FRAME + 24 + 100)
        byte = handle.read(1)
        handle.seek(-1, 1)
        handle.write(bytes([byte[0] ^ 0xFF]))
    with running(config) as daemon:
        lost = daemon.wait_event("spool_wal_frames_lost", 10)
        spool = daemon.status()["spool"]
        start = spool["start_check"]
        lost_frames = daemon.metric("fg_spool_wal_lost_frames")
        lost_commits = daemon.metric("fg_spool_wal_lost_commits")
    assert lost["level"] == "error"
    assert start["integrity"] == "ok"
    assert 0 < start["wal_lost_frames"] == lost["lost_frames"] == lost_frames
    assert 0 < start["wal_lost_commits"] == lost["lost_commits"] == lost_commits
    assert start["wal_problem"].endswith("fails its checksum")
    assert spool["state"] == "recovered_with_loss"
    assert f"{lost_commits:.0f} committed transactions" in spool["reason"]
    copy = Path(start["wal_copy"])
    assert copy.parent == tmp_path
    assert copy.name.startswith("spool.db-wal.corrupt-")
    assert (copy.stat().st_size - 32) // FRAME == frames


def test_a_damaged_database_is_moved_aside_and_the_gateway_starts(tmp_path: Path) -> None:
    port = free_udp_port()
    config = write_node(tmp_path, port)
    spool = tmp_path / "spool.db"
    spool.write_bytes(b"SQLite format 3\x00" + b"\xa5" * 8000)
    with running(config) as daemon:
        spool_status = daemon.status()["spool"]
        start = spool_status["start_check"]
        failures = daemon.metric("fg_spool_integrity_failures")
        wait_until(lambda: daemon.get("/readyz")[0] == 200, 10, "ready on the new spool")
    assert start["integrity"] == "corrupt"
    assert spool_status["state"] == "recovered_with_loss"
    assert "moved aside" in spool_status["reason"]
    assert failures == len(start["problems"]) >= 1
    moved = Path(start["moved_to"])
    assert moved.read_bytes().startswith(b"SQLite format 3\x00\xa5")
    assert daemon.events("spool_corrupt_moved_aside")[0]["level"] == "error"
