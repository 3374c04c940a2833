"""The klv sink's ffmpeg when things go wrong, through ``fischer-gateway run``.

A live test video (an ffmpeg test source streamed over UDP, as a camera's encoder would) and
``fischer-gateway simulate`` (F26E-001's camera at 5 Hz of sim time, three times real speed)
feed a daemon whose ``klv`` sink muxes both through its ffmpeg subprocess:

- ffmpeg stopped (SIGSTOP: any hang that leaves its stdin unread) must be killed, reaped and
  replaced, and the transport stream must flow again, not stay stuck in retries;
- the airframe's video going silent must end ffmpeg (naming why on ``/status``) rather than
  leave it waiting forever; once the video is back, video and KLV flow again.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from daemon_support import Daemon, free_udp_port, running, wait_until
from test_klv_run import Receiver, receiver
from tools import skip_without

FFMPEG = shutil.which("ffmpeg") or "ffmpeg"
pytestmark = [pytest.mark.timeout(180), skip_without("ffmpeg")]


def children(pid: int) -> dict[int, str]:
    """The child processes of ``pid``: {pid: state letter} (Linux /proc)."""
    found: dict[int, str] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        state, ppid = stat.rsplit(")", 1)[1].split()[:2]
        if int(ppid) == pid:
            found[int(entry.name)] = state
    return found


@contextmanager
def camera(port: int) -> Iterator[subprocess.Popen[bytes]]:
    command = [
        FFMPEG, "-v", "error", "-re", "-f", "lavfi", "-i", "testsrc=size=160x120:rate=10",
        "-t", "120", "-c:v", "mpeg2video", "-g", "10", "-f", "mpegts",
        f"udp://127.0.0.1:{port}?pkt_size=1316",
    ]  # fmt: skip
    process = subprocess.Popen(command, stdin=subprocess.DEVNULL)
    try:
        yield process
    finally:
        process.terminate()
        process.wait(10)


@contextmanager
def simulator(link: int) -> Iterator[None]:
    command = [sys.executable, "-m", "gateway", "simulate", "--scenario", "loitering-munitions",
               "--to", f"udp://127.0.0.1:{link}", "--duration", "300", "--speed", "3",
               "--no-resend"]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        yield
    finally:
        process.terminate()
        process.wait(10)


def write_config(tmp: Path, link: int, ts: int, video: int) -> Path:
    config = tmp / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 5}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured}}]}}
  - {{id: F26E-002, sysid: 2, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured}}]}}
sinks:
  - name: klv-001
    type: klv
    retry_max_s: 2
    options:
      mpegts: {{host: 127.0.0.1, port: {ts}, video: 'udp://127.0.0.1:{video}'}}
routes:
  - {{sinks: [klv-001], kinds: [video_frame_metadata], airframes: [F26E-001]}}
"""
    )
    return config


def ffmpeg_of(daemon: Daemon) -> set[int]:
    return set(children(daemon.proc.pid))


def flowing(ts: Receiver, daemon: Daemon) -> None:
    """Wait for fresh transport stream datagrams with video in them."""
    seen = len(ts.datagrams)
    wait_until(lambda: len(ts.datagrams) > seen + 30, 60.0, "MPEG-TS from ffmpeg")


def sink(daemon: Daemon) -> dict[str, object]:
    (found,) = [s for s in daemon.status()["sinks"] if s["sink"] == "klv-001"]
    return dict(found)


def test_a_stopped_ffmpeg_is_replaced_and_the_stream_resumes(tmp_path: Path) -> None:
    link, video = free_udp_port(), free_udp_port()
    with (
        receiver() as ts,
        camera(video),
        simulator(link),
        running(write_config(tmp_path, link, ts.port, video)) as daemon,
    ):
        flowing(ts, daemon)
        (stuck,) = ffmpeg_of(daemon)
        os.kill(stuck, signal.SIGSTOP)
        try:
            # Killed and reaped (no zombie left), and a new ffmpeg in its place.
            wait_until(lambda: stuck not in ffmpeg_of(daemon), 60.0, "stuck ffmpeg gone")
            wait_until(lambda: len(ffmpeg_of(daemon)) == 1, 60.0, "a new ffmpeg")
        finally:
            if stuck in ffmpeg_of(daemon):
                os.kill(stuck, signal.SIGCONT)
        flowing(ts, daemon)
        assert sink(daemon)["state"] == "open"
        stalled = [line for line in daemon.lines if "took no input" in str(line)]
        assert stalled, "the stall is reported"
        assert all(state != "Z" for state in children(daemon.proc.pid).values())


def test_video_gone_ends_ffmpeg_and_the_stream_resumes_when_it_is_back(tmp_path: Path) -> None:
    link, video = free_udp_port(), free_udp_port()
    with (
        receiver() as ts,
        simulator(link),
        running(write_config(tmp_path, link, ts.port, video)) as daemon,
    ):
        with camera(video):
            flowing(ts, daemon)
            (first,) = ffmpeg_of(daemon)
        # The video has gone silent: ffmpeg must give up, saying why, not hang on.
        wait_until(lambda: first not in ffmpeg_of(daemon), 60.0, "ffmpeg to give up")
        wait_until(lambda: "ffmpeg" in str(sink(daemon)["reason"]), 30.0, "the reason")
        with camera(video):
            flowing(ts, daemon)
            wait_until(lambda: sink(daemon)["state"] == "open", 30.0, "the sink open")
