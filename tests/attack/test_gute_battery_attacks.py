"""A hostile GUTE II battery against the daemon as operators run it.

``fischer-gateway run --config FILE`` in a child process: one airframe on loopback UDP reporting
a loitering munition near the battery, processors ``fusion`` and ``counter_uas`` and a ``gute2``
sink to a real HTTPS battery (client certificate required) that answers the first POSTs with
garbage, a 40 kB head, 500 headers, a connection closed mid-answer, a broken chunked body and a
trickle of header bytes (``hostile_https_peer.HOSTILE``), then honestly.

The daemon must neither crash nor hang on any of them: each is a retry (logged naming the URL
and what was wrong), and the cue then reaches the battery, once, still only a recommendation.

A second battery stalls, floods and lies (``WORSE``): 20 interim answers, a 30-digit or an
unkept Content-Length, a chunk size of 40 hex digits or negative, a garbage or huge Retry-After,
a redirect, a 503 with a 100 MB body, a slowloris status line and a kept connection closed
unanswered. Each ends by the POST's deadline as a retry, the runner does not log a line per
answer, and the cue arrives once.
"""

from __future__ import annotations

import json
import socket
from pathlib import Path

import pytest
from daemon_support import Airframe, free_udp_port, running, wait_until
from hostile_https_peer import HOSTILE, Script, ScriptedPeer

from gateway.fleet.dialect import fischer_detection

pytestmark = pytest.mark.timeout(90)

BATTERY = (65.80, 21.70)
#: The munition, ~3 km north of the battery.
TARGET = (round((BATTERY[0] + 0.027) * 1e7), round(BATTERY[1] * 1e7))


def write_config(tmp_path: Path, peer: ScriptedPeer, link: int) -> Path:
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}
processors:
  - {{name: fusion, type: fusion}}
  - name: cuas
    type: counter_uas
    options:
      batteries: [{{id: GUTE-1, lat_deg: {BATTERY[0]}, lon_deg: {BATTERY[1]},
                    effectors: [EW_COUNTERMEASURES]}}]
sinks:
  - name: gute
    type: gute2
    options: {{url: '{peer.url}', ca_file: '{peer.ca_file}', cert_file: '{peer.cert_file}',
               key_file: '{peer.key_file}', timeout_s: 1.0}}
    retry_initial_s: 0.05
    retry_max_s: 0.2
routes:
  - {{sinks: [gute], kinds: [handoff]}}
"""
    )
    return config


def test_every_hostile_answer_is_a_named_retry_and_the_cue_arrives_once(
    tmp_path: Path,
) -> None:
    link = free_udp_port()
    airframe = Airframe(1)
    peer = ScriptedPeer(tmp_path / "pki", list(HOSTILE))
    with peer.in_thread(), running(write_config(tmp_path, peer, link)) as daemon:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
            out.connect(("127.0.0.1", link))

            def detect() -> bool:
                airframe.detections += 1
                frame = fischer_detection(
                    time_usec=0,
                    detection_id=airframe.detections,
                    lat_e7=TARGET[0],
                    lon_e7=TARGET[1],
                    alt_msl_m=120.0,
                    sigma_h_m=5.0,
                    class_id=5,  # loitering munition
                    sensor=1,
                    confidence_pct=97,
                    frame_size=1,
                )
                out.send(bytes(frame.pack(airframe.mav)))
                return bool(peer.accepted)

            wait_until(detect, 30.0, "a cue accepted by the battery after the hostile answers")
        retries = [line for line in daemon.lines if peer.url in json.dumps(line)]
        assert daemon.proc.poll() is None
        assert daemon.status()
    assert peer.played == [s.name for s in HOSTILE]
    # The runner logs the first failures of a row (then its circuit opens and it paces its
    # lines); each names the URL and what was wrong. All the answers are in test_http1.
    reasons = "\n".join(json.dumps(line) for line in retries)
    for what in ("not an HTTP/1.1 answer", "longer than 16384 bytes", "more than 100 header"):
        assert what in reasons, reasons
    ((key, body),) = peer.accepted.items()
    cue = json.loads(body)
    assert cue["handoff_id"] == key
    assert cue["operator_authorisation_required"] is True
    # The cue's key reached the battery once per answer it got, never more.
    assert peer.keys.count(key) == len(HOSTILE) + 1


_CREATED = b"HTTP/1.1 201 Created\r\n"
_MB = b"x" * 1_000_000

#: Beyond ``HOSTILE``: answers that stall, lie about their length, flood or redirect.
WORSE = [
    Script("1xx flood", (b"HTTP/1.1 100 Continue\r\n\r\n" * 20,), close=False),
    Script("huge length, no body", (_CREATED + b"Content-Length: " + b"9" * 30 + b"\r\n\r\n",)),
    Script("length, body never sent", (_CREATED + b"Content-Length: 50\r\n\r\n{",), close=False),
    Script(
        "huge chunk",
        (_CREATED + b"Transfer-Encoding: chunked\r\n\r\n" + b"f" * 40 + b"\r\nab",),
        close=False,
    ),
    Script("negative chunk", (_CREATED + b"Transfer-Encoding: chunked\r\n\r\n-5\r\nab",)),
    Script(
        "bad Retry-After",
        (b"HTTP/1.1 503 Busy\r\nRetry-After: -1e400\r\nContent-Length: 0\r\n\r\n",),
    ),
    Script(
        "huge Retry-After",
        (b"HTTP/1.1 429 Slow\r\nRetry-After: " + b"9" * 60 + b"\r\nContent-Length: 0\r\n\r\n",),
        close=False,
    ),
    Script(
        "redirect",
        (b"HTTP/1.1 307 Moved\r\nLocation: https://evil.example/x\r\nContent-Length: 0\r\n\r\n",),
        close=False,
    ),
    # 100 MB of a 5xx's reason, then of a 409's: read up to a bound, the connection dropped.
    Script("503 with 100 MB", (b"HTTP/1.1 503 Busy\r\n\r\n",) + (_MB,) * 100),
    Script("slowloris head", (b"HTTP/1.1 2",) + (b"0",) * 100, pause_s=0.05),
    Script("kept, then closed unanswered", (), delay_s=0.05),
]


def test_stalls_floods_and_lies_are_retries_and_the_cue_arrives_once(tmp_path: Path) -> None:
    link = free_udp_port()
    airframe = Airframe(1)
    peer = ScriptedPeer(tmp_path / "pki", list(WORSE))
    with peer.in_thread(), running(write_config(tmp_path, peer, link)) as daemon:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
            out.connect(("127.0.0.1", link))

            def detect() -> bool:
                airframe.detections += 1
                frame = fischer_detection(
                    time_usec=0,
                    detection_id=airframe.detections,
                    lat_e7=TARGET[0],
                    lon_e7=TARGET[1],
                    alt_msl_m=120.0,
                    sigma_h_m=5.0,
                    class_id=5,
                    sensor=1,
                    confidence_pct=97,
                    frame_size=1,
                )
                out.send(bytes(frame.pack(airframe.mav)))
                return bool(peer.accepted)

            wait_until(detect, 60.0, "a cue accepted by the battery after the worse answers")
        assert daemon.proc.poll() is None
        assert daemon.status()
        lines = list(daemon.lines)
    assert peer.played == [s.name for s in WORSE]
    ((key, body),) = peer.accepted.items()
    assert json.loads(body)["operator_authorisation_required"] is True
    assert peer.keys.count(key) == len(WORSE) + 1
    # The runner paces its lines: not one per answer.
    about = [line for line in lines if peer.url in json.dumps(line)]
    assert len(about) <= len(WORSE), about
