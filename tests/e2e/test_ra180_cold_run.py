"""The Ra 180 sink tried cold, through ``fischer-gateway run``, where the network or the node
is not as the config assumed.

- The radio gateway is not listening yet (its port answers ICMP port unreachable): the new
  target's ``MAL`` must not be lost while ``/status`` says ``sending``; the sink must show
  ``waiting for radio`` and send the ``MAL`` once the gateway listens.
- The voice directory is shared with other audio (a player's folder): keeping it to
  ``max_files`` removes only the announcements, never the other WAV files.
- The synthesiser hangs: the messages still go out, the rendering is killed at its deadline
  and counted with a clear reason; partial files a stopped gateway left are removed.
- espeak-ng is installed while the gateway runs: the next new target is spoken, without a
  restart, and the unavailability was logged once.

One airframe on loopback UDP reports a tank (a hostile class); the ``fusion`` processor
makes the track and routes it to the ``ra180`` sink.
"""

from __future__ import annotations

import shutil
import socket
import time
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Airframe, Daemon, free_udp_port, running, wait_until

from gateway.fleet.dialect import fischer_detection
from sinks.ra180.cdm import parse_cdm

pytestmark = pytest.mark.timeout(90)


def write_config(tmp_path: Path, link: int, radio_port: int, voice: str = "") -> Path:
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - id: F1
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured, name: l1}}]
processors:
  - name: fusion
    type: fusion
    # One detection is a track here (the radio path is under test, not M-of-N confirmation).
    options: {{update_interval_s: 0.2, tick_s: 0.2, confirm_hits: 1, confirm_window: 1}}
sinks:
  - name: radio
    type: ra180
    options:
      udp: {{host: 127.0.0.1, port: {radio_port}}}
      retry_initial_s: 0.2
      retry_max_s: 0.5
{voice}
routes:
  - {{kinds: [track], sinks: [radio]}}
"""
    )
    return config


def detail(daemon: Daemon) -> dict[str, Any]:
    (sink,) = [s for s in daemon.status()["sinks"] if s["sink"] == "radio"]
    return sink["detail"]  # type: ignore[no-any-return]


def report_a_tank(link: int) -> None:
    airframe = Airframe(1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.sendto(airframe.heartbeat(), ("127.0.0.1", link))
        sock.sendto(airframe.detection(), ("127.0.0.1", link))


def test_a_new_target_waits_for_a_radio_gateway_that_is_not_listening_yet(
    tmp_path: Path,
) -> None:
    link, radio_port = free_udp_port(), free_udp_port()  # nothing listens on radio_port yet
    with running(write_config(tmp_path, link, radio_port)) as daemon:
        report_a_tank(link)
        wait_until(lambda: detail(daemon)["radio_state"] == "waiting for radio", 30, "refused")
        waiting = detail(daemon)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as radio:
            radio.bind(("127.0.0.1", radio_port))
            radio.settimeout(30)
            first = parse_cdm(radio.recv(1024).decode("ascii"))
            wait_until(lambda: detail(daemon)["radio_state"] == "sending", 30, "sending again")
            final = detail(daemon)
    assert "refused" in waiting["radio_reason"].lower()
    assert waiting["sent"] == 0
    assert waiting["held"] == 1
    assert (first.type, first.number, first.class_abbreviation) == ("MAL", 1, "STRV")
    assert (final["sent_new"], final["held"]) == (1, 0)


def test_keeping_a_shared_voice_directory_small_removes_only_announcements(
    tmp_path: Path,
) -> None:
    if shutil.which("espeak-ng") is None:
        pytest.skip("espeak-ng is not installed (Debian package espeak-ng)")
    shared = tmp_path / "audio"
    shared.mkdir()
    theirs = [shared / "0000-call-sign.wav", shared / "alarm.wav"]
    for path in theirs:
        path.write_bytes(b"RIFF not ours")
    directory = tmp_path / "voice"
    directory.symlink_to(shared)  # as an operator links the player's folder
    voice = f"      voice: {{directory: '{directory}', max_files: 1}}"
    link = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as radio:
        radio.bind(("127.0.0.1", 0))
        radio.settimeout(30)
        config = write_config(tmp_path, link, radio.getsockname()[1], voice)
        with running(config) as daemon:
            report_a_tank(link)
            assert radio.recv(1024).startswith(b"MAL FIENDE STRV ")
            wait_until(lambda: detail(daemon)["voice"]["rendered"] == 1, 60, "the announcement")
    ours = [p for p in shared.glob("*.wav") if p not in theirs]
    assert len(ours) == 1
    assert ours[0].name.endswith("-NR0001-MAL.wav")
    assert all(path.read_bytes() == b"RIFF not ours" for path in theirs)


def test_a_hanging_synthesiser_neither_holds_the_net_nor_leaves_files(tmp_path: Path) -> None:
    hanging = tmp_path / "espeak-ng"
    hanging.write_text("#!/bin/sh\nexec sleep 600\n")
    hanging.chmod(0o755)
    directory = tmp_path / "voice"
    directory.mkdir()
    stale = directory / ".20261125T203421920410Z-000001-NR0001-MAL.wav.part"  # a crash's
    stale.write_bytes(b"RIFF")
    voice = f"      voice: {{directory: '{directory}', program: '{hanging}', timeout_s: 1}}"
    link = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as radio:
        radio.bind(("127.0.0.1", 0))
        radio.settimeout(30)
        config = write_config(tmp_path, link, radio.getsockname()[1], voice)
        with running(config) as daemon:
            report_a_tank(link)
            assert radio.recv(1024).startswith(b"MAL FIENDE STRV ")
            wait_until(lambda: detail(daemon)["voice"]["failed"] == 1, 30, "the deadline")
            final = detail(daemon)["voice"]
    assert final["reason"] == f"{hanging} did not finish within 1 s"
    assert final["rendered"] == 0
    assert list(directory.iterdir()) == []


def test_espeak_installed_while_running_brings_the_voice_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    espeak = shutil.which("espeak-ng")
    if espeak is None:
        pytest.skip("espeak-ng is not installed (Debian package espeak-ng)")
    path = tmp_path / "bin"  # the daemon's PATH: empty until the package is "installed"
    path.mkdir()
    monkeypatch.setenv("PATH", str(path))
    directory = tmp_path / "voice"
    link = free_udp_port()
    airframe = Airframe(1)
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as radio,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock,
    ):
        radio.bind(("127.0.0.1", 0))
        radio.settimeout(30)
        config = write_config(
            tmp_path, link, radio.getsockname()[1], f"      voice: {{directory: '{directory}'}}"
        )
        with running(config) as daemon:
            sock.sendto(airframe.heartbeat(), ("127.0.0.1", link))
            sock.sendto(airframe.detection(), ("127.0.0.1", link))
            assert parse_cdm(radio.recv(1024).decode("ascii")).number == 1
            wait_until(lambda: detail(daemon)["voice"]["unavailable"] == 1, 30, "unavailable")
            (path / "espeak-ng").symlink_to(espeak)
            far = fischer_detection(  # a second tank 5.5 km north: a new target
                time_usec=round(time.time() * 1e6),
                detection_id=99,
                lat_e7=593_800_000,
                lon_e7=181_000_000,
                alt_msl_m=30.0,
                sigma_h_m=8.0,
                class_id=1,
                sensor=1,
                confidence_pct=91,
                subtype="T-72",
            )
            sock.sendto(bytes(far.pack(airframe.mav)), ("127.0.0.1", link))
            assert parse_cdm(radio.recv(1024).decode("ascii")).number == 2
            wait_until(lambda: detail(daemon)["voice"]["rendered"] == 1, 60, "the voice back")
            voice = detail(daemon)["voice"]
            events = [line.get("event") for line in daemon.lines]
    assert (voice["state"], voice["reason"], voice["unavailable"]) == ("ready", "", 1)
    assert [p.name[-15:] for p in directory.glob("*.wav")] == ["-NR0002-MAL.wav"]
    assert events.count("ra180_voice_unavailable") == 1
    assert events.count("ra180_voice_ready") == 1
