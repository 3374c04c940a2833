"""Each hostile vehicle is announced to the Ra 180 net exactly once as new, through ``run``.

``fischer-gateway run --config FILE`` in a child process: two airframes on loopback UDP, the
``fusion`` processor, a jsonl archive and an ``ra180`` sink to a UDP socket this test holds
as the radio net. ``fischer-gateway simulate --scenario parked-vehicles`` plays its first 30 s
(five BMP-2 30 m apart, EO σ 15 m, IR σ 20 m) at four times real speed and writes its truth.

A "new target" (``MAL``) message carries a 10 m grid reference of the track's estimate when
it was composed, which can be nearer a neighbour 30 m away than its own vehicle; it also
carries the sink's target number, one per track. Traced through that number to the track it
announces (``gateway.scoring.announce``), and through the scorer to the vehicle, each of the
five must be announced exactly once, and no message may be left untraced.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from daemon_support import free_udp_port, running, wait_until

from gateway.scoring.announce import announcements_by_track
from gateway.scoring.files import archive_tracks, read_archive, read_truth
from gateway.scoring.score import score
from sinks.ra180.cdm import Cdm, CdmError, parse_cdm

pytestmark = pytest.mark.timeout(120)

SPEED = 4.0
VEHICLES = ["PV-1", "PV-2", "PV-3", "PV-4", "PV-5"]


class RadioNet:
    """The net's side of the ``ra180`` sink: every CDM heard, in order."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = int(self.sock.getsockname()[1])
        self.heard: list[Cdm] = []
        self.garbled: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(2048)
            except TimeoutError:
                continue
            try:
                self.heard.append(parse_cdm(data.decode("ascii")))
            except (CdmError, UnicodeDecodeError):
                self.garbled.append(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.sock.close()


def write_config(tmp_path: Path, link: int, radio: int) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    fleet = f"links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured, name: fleet}}]"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, {fleet}}}
  - {{id: F26E-002, sysid: 2, {fleet}}}
processors:
  - {{name: fusion, type: fusion, options: {{speed_scale: {SPEED:g}}}}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
  - {{name: radio, type: ra180, options: {{udp: {{host: 127.0.0.1, port: {radio}}}}}}}
routes:
  - {{kinds: [track], sinks: [archive, radio]}}
"""
    )
    return config, archive


def test_each_parked_vehicle_is_announced_once_as_new(tmp_path: Path) -> None:
    link = free_udp_port()
    radio = RadioNet()
    truth_file = tmp_path / "truth.jsonl"
    try:
        config, archive = write_config(tmp_path, link, radio.port)
        with running(config):
            command = [sys.executable, "-m", "gateway", "simulate"]
            command += ["--scenario", "parked-vehicles", "--duration", "30"]
            command += ["--speed", str(SPEED), "--truth", str(truth_file)]
            command += ["--to", f"udp://127.0.0.1:{link}"]
            played = subprocess.run(command, capture_output=True, timeout=60, check=False)
            assert played.returncode == 0, played.stderr.decode(errors="replace")

            def five_announced() -> bool:
                return len({c.number for c in radio.heard if c.type == "MAL"}) >= len(VEHICLES)

            wait_until(five_announced, 20.0, "five new targets heard on the net")
    finally:
        radio.close()
    assert radio.garbled == []
    truth = read_truth(truth_file)
    scored = score(truth, read_archive([archive], truth.plane))
    counted = announcements_by_track(
        radio.heard, archive_tracks([archive]), scored.tracks_of_target, VEHICLES
    )
    assert counted.per_target == dict.fromkeys(VEHICLES, 1), (counted, scored.tracks_of_target)
    assert (counted.untraced, counted.false_track) == (0, 0), counted
    # One "new" per number: an announced track is never announced new again.
    news = [c.number for c in radio.heard if c.type == "MAL"]
    assert len(news) == len(set(news)) == len(VEHICLES)
