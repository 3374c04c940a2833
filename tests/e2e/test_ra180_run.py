"""The Ra 180 sink in the daemon as operators run it: a hostile track to a UDP radio gateway.

``fischer-gateway run --config FILE`` in a child process with two unsecured airframes on
loopback UDP, the ``fusion`` processor and the ``ra180`` sink sending to a UDP socket here
(the radio gateway) with the Swedish voice on. Airframe 1 reports a loitering munition on
EO; the radio gateway must get one CDM announcing it (``MAL FIENDE LUFT-MUN``) whose grid
reference decodes, with the ``mgrs`` package, to where it was reported, and a WAV file of the
announcement must be written. Airframe 2 then sees it 2 m away on IR: the track is updated,
but the net is not told again (a repeat, suppressed and counted on ``/status``).
"""

from __future__ import annotations

import os
import shutil
import socket
import time
import wave
from pathlib import Path

import mgrs
import pytest
from daemon_support import Airframe, free_udp_port, running, wait_until
from geographiclib.geodesic import Geodesic

from gateway.fleet.dialect import fischer_detection
from sinks.ra180.cdm import parse_cdm

pytestmark = pytest.mark.timeout(90)

LAT_E7, LON_E7 = 658_235_000, 216_955_000


def write_config(tmp_path: Path, ports: list[int], radio_port: int) -> Path:
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - id: F1
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{ports[0]}', security: unsecured, name: l1}}]
  - id: F2
    sysid: 2
    links: [{{uri: 'udp://127.0.0.1:{ports[1]}', security: unsecured, name: l2}}]
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
      originator: Jägare1
      voice: {{directory: '{tmp_path / "wav"}'}}
routes:
  - {{kinds: [track], sinks: [radio]}}
"""
    )
    return config


def detection_frame(airframe: Airframe, *, sensor: int, confidence_pct: int, dlat_e7: int) -> bytes:
    airframe.detections += 1
    message = fischer_detection(
        time_usec=round(time.time() * 1e6),
        detection_id=airframe.detections,
        lat_e7=LAT_E7 + dlat_e7,
        lon_e7=LON_E7,
        alt_msl_m=250.0,
        sigma_h_m=8.0,
        class_id=5,  # loitering_munition
        sensor=sensor,
        confidence_pct=confidence_pct,
        subtype="LANCET",
    )
    return bytes(message.pack(airframe.mav))


def test_a_hostile_track_reaches_the_radio_gateway_and_is_announced(tmp_path: Path) -> None:
    ports = [free_udp_port(), free_udp_port()]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as radio:
        radio.bind(("127.0.0.1", 0))
        radio.settimeout(30)
        config = write_config(tmp_path, ports, radio.getsockname()[1])
        one, two = Airframe(1), Airframe(2)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock, running(config) as daemon:
            sock.sendto(one.heartbeat(), ("127.0.0.1", ports[0]))
            sock.sendto(two.heartbeat(), ("127.0.0.1", ports[1]))
            eo = detection_frame(one, sensor=0, confidence_pct=80, dlat_e7=0)
            sock.sendto(eo, ("127.0.0.1", ports[0]))
            datagram = radio.recv(1024)
            ir = detection_frame(two, sensor=1, confidence_pct=75, dlat_e7=20)  # 2 m north
            sock.sendto(ir, ("127.0.0.1", ports[1]))

            def detail() -> dict[str, object]:
                (sink,) = [s for s in daemon.status()["sinks"] if s["sink"] == "radio"]
                return sink["detail"]  # type: ignore[no-any-return]

            wait_until(lambda: int(detail()["suppressed"]) >= 1, 20, "the repeat suppressed")
            espeak = shutil.which("espeak-ng")
            if espeak is None and "espeak-ng" in os.environ.get("FG_REQUIRED_TOOLS", "").split():
                pytest.fail("espeak-ng is required here (FG_REQUIRED_TOOLS) but not on PATH")
            if espeak is not None:
                wait_until(lambda: any((tmp_path / "wav").glob("*.wav")), 30, "the WAV")
            else:
                wait_until(lambda: detail()["voice"]["state"] == "unavailable", 20, "no voice")  # type: ignore[index]
            final = detail()
            metrics = {
                outcome: daemon.metric("fg_sink_outcomes_total", sink="radio", outcome=outcome)
                for outcome in ("sent", "suppressed", "held_back")
            }
    text = datagram.decode("ascii")
    cdm = parse_cdm(text)
    assert text.startswith("MAL FIENDE LUFT-MUN POS ")
    assert text.endswith(" FRAN JAGARE1")
    assert (cdm.type, cdm.confidence_pct, cdm.number) == ("MAL", 80, 1)
    lat, lon = mgrs.MGRS().toLatLon(cdm.mgrs.replace(" ", ""))
    reported = Geodesic.WGS84.Inverse(LAT_E7 / 1e7, LON_E7 / 1e7, lat, lon)["s12"]
    assert reported < 7.1 + 1.0  # the 10 m cell's centre, plus a fused track's wobble
    assert (final["sent_new"], final["sent_update"], final["held"]) == (1, 0, 0)
    assert final["radio_state"] == "sending"
    assert metrics["sent"] == 1
    assert metrics["suppressed"] >= 1
    assert metrics["held_back"] == 0  # one message is well within the default budget
    if espeak is None:
        assert "install the Debian package espeak-ng" in final["voice"]["reason"]  # type: ignore[index]
        return
    (wav,) = (tmp_path / "wav").glob("*.wav")
    assert wav.name.endswith("-NR0001-MAL.wav")
    with wave.open(str(wav)) as audio:
        assert audio.getnframes() / audio.getframerate() > 10
