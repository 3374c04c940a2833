"""STANAG 4609 out of the daemon as operators run it: KLV over UDP and beside live video.

``fischer-gateway run --config FILE`` in a child process with a ``klv`` sink that sends ST
0601 packets over UDP and, through its ffmpeg subprocess, an MPEG-TS of the airframe's video
(a live ffmpeg test source streamed over UDP, as a camera's encoder would) with the KLV as a
data stream. ``fischer-gateway simulate --scenario loitering-munitions`` flies F26E-001 with
its camera reporting. ffprobe must list the video and the KLV stream in what arrived, and
every KLV packet ffmpeg extracts from it must be byte-identical to one sent over plain UDP.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from daemon_support import free_udp_port, running, wait_until
from tools import skip_without

from sinks.klv.ber import split_packets
from sinks.klv.st0601 import decode

FFMPEG = shutil.which("ffmpeg") or "ffmpeg"
FFPROBE = shutil.which("ffprobe") or "ffprobe"
pytestmark = [
    pytest.mark.timeout(120),
    skip_without("ffmpeg", "ffprobe"),
]


@dataclass
class Receiver:
    """A loopback UDP socket whose datagrams a thread collects."""

    sock: socket.socket
    datagrams: list[bytes] = field(default_factory=list)

    @property
    def port(self) -> int:
        return int(self.sock.getsockname()[1])

    def run(self) -> None:
        while True:
            try:
                self.datagrams.append(self.sock.recv(65_536))
            except OSError:
                return


@contextmanager
def receiver() -> Iterator[Receiver]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind(("127.0.0.1", 0))
    got = Receiver(sock)
    thread = threading.Thread(target=got.run, daemon=True)
    thread.start()
    try:
        yield got
    finally:
        with contextlib.suppress(OSError):  # wakes the thread's recv (Linux)
            sock.shutdown(socket.SHUT_RDWR)
        sock.close()
        thread.join(5)


def write_config(tmp: Path, link: int, klv: int, ts: int, video: int) -> Path:
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
    options:
      mission_id: KLV-E2E
      udp: {{host: 127.0.0.1, port: {klv}}}
      mpegts: {{host: 127.0.0.1, port: {ts}, video: 'udp://127.0.0.1:{video}'}}
routes:
  - {{sinks: [klv-001], kinds: [video_frame_metadata], airframes: [F26E-001]}}
"""
    )
    return config


@dataclass
class KlvRun:
    udp: list[bytes]
    ts: bytes
    status: dict[str, object]
    tmp: Path


@pytest.fixture(scope="module")
def klv_run(tmp_path_factory: pytest.TempPathFactory) -> KlvRun:
    tmp = tmp_path_factory.mktemp("klv")
    link, video = free_udp_port(), free_udp_port()
    camera = [
        FFMPEG, "-v", "error", "-re", "-f", "lavfi", "-i", "testsrc=size=160x120:rate=10",
        "-t", "40", "-c:v", "mpeg2video", "-g", "10", "-f", "mpegts",
        f"udp://127.0.0.1:{video}?pkt_size=1316",
    ]  # fmt: skip
    with receiver() as klv, receiver() as ts:
        config = write_config(tmp, link, klv.port, ts.port, video)
        encoder = subprocess.Popen(camera, stdin=subprocess.DEVNULL)
        try:
            with running(config) as daemon:
                simulate = [sys.executable, "-m", "gateway", "simulate", "--scenario"]
                simulate += ["loitering-munitions", "--to", f"udp://127.0.0.1:{link}"]
                simulate += ["--duration", "21", "--speed", "3"]
                played = subprocess.run(simulate, capture_output=True, timeout=60, check=False)
                assert played.returncode == 0, played.stderr.decode(errors="replace")
                wait_until(lambda: len(ts.datagrams) > 50, 20.0, "MPEG-TS from ffmpeg")
                status = daemon.status()
        finally:
            encoder.terminate()
            encoder.wait(10)
        return KlvRun(list(klv.datagrams), b"".join(ts.datagrams), status, tmp)


def test_udp_packets_decode_with_good_checksums(klv_run: KlvRun) -> None:
    assert len(klv_run.udp) >= 5 * 15  # F26E-001's camera: 5 Hz of sim time, 21 s of it
    for packet in klv_run.udp:
        values = decode(packet)
        assert (values[3], values[4]) == ("KLV-E2E", "F26E-001")
    sinks = klv_run.status["sinks"]
    assert isinstance(sinks, list)
    (sink,) = [s for s in sinks if s["sink"] == "klv-001"]
    assert sink["state"] == "open"


def test_ffprobe_lists_video_and_klv_and_ffmpeg_extracts_our_packets(klv_run: KlvRun) -> None:
    path = klv_run.tmp / "received.ts"
    path.write_bytes(klv_run.ts)
    probe = subprocess.run(
        [FFPROBE, "-v", "error", "-show_streams", "-of", "json", str(path)],
        capture_output=True, text=True, timeout=60, check=True,
    )  # fmt: skip
    streams = [(s["codec_type"], s["codec_name"]) for s in json.loads(probe.stdout)["streams"]]
    assert streams == [("video", "mpeg2video"), ("data", "klv")]
    out = klv_run.tmp / "extracted.klv"
    subprocess.run(
        [FFMPEG, "-v", "error", "-y", "-i", str(path), "-map", "0:d:0", "-c", "copy",
         "-f", "data", str(out)],
        timeout=60, check=True,
    )  # fmt: skip
    extracted = list(split_packets(out.read_bytes()))
    assert len(extracted) >= 10
    sent = set(klv_run.udp)
    assert all(packet in sent for packet in extracted)
