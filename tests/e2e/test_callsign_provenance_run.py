"""A CoT callsign from an unauthenticated sender, through ``fischer-gateway run --config FILE``.

A red team's ATAK device calls itself "WEAPONS FREE - ENGAGE AUTHORISED BY BDE" (with a bidi
override in it) and stands 110 m from a loitering munition one airframe reports. The GUTE II
battery (a real HTTPS peer checking every body against the shipped schema) must get the cue
with that callsign cut to the safe alphabet and length and marked "unauthenticated CoT
callsign" from source ``atak-mesh``, and the blue-force picture counted by source and
provenance (the CoT unit unauthenticated, the unit fixed in the config ``configured``). The
story (console sink) shows the callsign only quoted and marked, never the bare text.
"""

from __future__ import annotations

import socket
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from daemon_support import Airframe, free_udp_port, running, wait_until
from gute_peer import GutePeer

from gateway.fleet.dialect import fischer_detection

pytestmark = pytest.mark.timeout(90)

HOSTILE = "WEAPONS FREE\u202e - ENGAGE AUTHORISED BY BDE"
SAFE = "WEAPONS FREE - ENGAGE AUTHORI..."
LAT, LON = 65.8, 21.7


def write_config(tmp_path: Path, peer: GutePeer, link: int, cot: int) -> tuple[Path, Path]:
    story = tmp_path / "story.txt"
    gute = peer.sink_options()
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - {{id: F1, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured}}]}}
sources:
  - {{name: atak-mesh, uri: 'udp://127.0.0.1:{cot}'}}
processors:
  - {{name: fusion, type: fusion}}
  - name: cuas
    type: counter_uas
    options:
      min_confidence: 0.5
      batteries: [{{id: GUTE-1, lat_deg: {LAT + 0.01}, lon_deg: {LON},
                    effectors: [TRACKFIRE_30MM]}}]
      blue_forces: [{{uid: PLT-1, callsign: 1. pluton, lat_deg: {LAT + 0.1}, lon_deg: {LON}}}]
sinks:
  - name: gute
    type: gute2
    options: {{url: '{gute["url"]}', ca_file: '{gute["ca_file"]}',
               cert_file: '{gute["cert_file"]}', key_file: '{gute["key_file"]}'}}
  - {{name: story, type: console, options: {{format: story, output: '{story}'}}}}
routes:
  - {{sinks: [gute], kinds: [handoff]}}
  - {{sinks: [story], kinds: [blue_force, track, handoff]}}
"""
    )
    return config, story


def hostile_report() -> bytes:
    now = datetime.now(UTC)
    stamp = now.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
    stale = (now + timedelta(minutes=5)).strftime("%Y-%m-%dT%H:%M:%S.000Z")
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n<event version="2.0" uid="ANDROID-RED" '
        f'type="a-f-G-U-C" how="m-g" time="{stamp}" start="{stamp}" stale="{stale}">'
        f'<point lat="{LAT + 0.001}" lon="{LON}" hae="9999999.0" ce="9999999.0" le="9999999.0"/>'
        f'<detail><contact callsign="{HOSTILE}"/></detail></event>'
    ).encode()


def munition(airframe: Airframe) -> bytes:
    airframe.detections += 1
    message = fischer_detection(
        time_usec=round(time.time() * 1e6),
        detection_id=airframe.detections,
        lat_e7=round(LAT * 1e7),
        lon_e7=round(LON * 1e7),
        alt_msl_m=250.0,
        sigma_h_m=8.0,
        class_id=5,  # loitering_munition
        sensor=0,
        confidence_pct=80,
        subtype="LANCET",
    )
    return bytes(message.pack(airframe.mav))


def test_an_unauthenticated_callsign_reaches_the_cue_and_story_only_safe_and_marked(
    tmp_path: Path,
) -> None:
    link, cot = free_udp_port(), free_udp_port()
    airframe = Airframe(1)
    with (
        GutePeer(tmp_path / "pki").in_thread() as peer,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock,
    ):
        config, story = write_config(tmp_path, peer, link, cot)
        with running(config) as daemon:
            sock.sendto(hostile_report(), ("127.0.0.1", cot))

            def registered() -> bool:
                (cuas,) = [p for p in daemon.status()["processors"] if p["processor"] == "cuas"]
                return bool(cuas["detail"]["blue_units"] == 2)

            wait_until(registered, 15, "the CoT unit and the fixed one registered")
            sock.sendto(airframe.heartbeat(), ("127.0.0.1", link))
            for _ in range(3):  # a track is published once confirmed (3 of 5 detections)
                sock.sendto(munition(airframe), ("127.0.0.1", link))
                time.sleep(0.3)
            wait_until(lambda: bool(peer.accepted), 20, "the cue accepted by the battery")
            wait_until(
                lambda: "GUTE II cue" in story.read_text(encoding="utf-8"), 10, "the story told"
            )
    (document,) = peer.accepted.values()
    assert document["schema"] == "fischer-gateway/gute2-handoff/2"
    check = document["deconfliction"]
    assert check["clear"] is False  # 110 m: inside TRACKFIRE's danger close
    assert check["nearest_blue_uid"] == "ANDROID-RED"
    assert check["nearest_blue_callsign"] == SAFE
    assert check["nearest_blue_callsign_provenance"] == "unauthenticated CoT callsign"
    assert check["nearest_blue_source"] == "atak-mesh"
    assert check["nearest_blue_provenance"] == "unauthenticated"
    assert sorted(check["blue_sources"], key=lambda s: s["source"]) == [
        {"source": "atak-mesh", "provenance": "unauthenticated", "units": 1},
        {"source": "cuas", "provenance": "configured", "units": 1},
    ]
    lines = story.read_text(encoding="utf-8").splitlines()
    marked = f'"{SAFE}" (unauthenticated CoT callsign, source atak-mesh)'
    assert any(f"nearest blue {marked} at " in line for line in lines), lines
    assert any(f'blue force registered: {marked}, uid "ANDROID-RED",' in line for line in lines)
    assert any('"1. pluton" (configured callsign, source cuas)' in line for line in lines)
    text = "\n".join(lines)
    assert "AUTHORISED BY BDE" not in text
    assert "\u202e" not in text
    for line in lines:  # wherever the callsign shows, its provenance follows it
        if "WEAPONS" in line:
            assert f"{marked}" in line, line
