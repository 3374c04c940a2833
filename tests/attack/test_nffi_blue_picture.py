"""An NFFI peer against the blue-force picture, through ``fischer-gateway run --config FILE``.

A report under the uid of a unit fixed by orders (``counter_uas`` ``blue_forces``) must not
reach any sink: the CoT sink would draw the fixed unit wherever the report says. Nor may our
own airframe's track come back in (a C2 system echoing what our ``nffi`` sink sent it, or a
forgery) as a second, "friendly" unit.

A flood of friendly reports larger than the ``counter_uas`` processor's inbox: the reports it
never got may have held a real unit's newest position, so the picture must then say it is
incomplete (cues never "clear"), not silently keep deconflicting against what is left.
"""

from __future__ import annotations

import contextlib
import json
import socket
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Daemon, free_tcp_port, free_udp_port, running, wait_until

from gateway.events import BlueForce, Position
from sinks.nffi.codec import NffiOptions, encode_message, tracks_of

pytestmark = pytest.mark.timeout(120)


def friendly_reports(
    count: int, at: datetime, system: str = "FLOOD", lat: float = 65.0, name: str = "U{n}"
) -> bytes:
    """One NFFI document with ``count`` distinct friendly ground units (``U0`` ...)."""
    units = [
        BlueForce(
            event_id="-",
            uid=name.format(n=n),
            time=at,
            position=Position(lat_deg=lat + n * 1e-4, lon_deg=21.0),
            source="-",
        )
        for n in range(count)
    ]
    return encode_message(tracks_of(units, NffiOptions(system=system, country="SWE")))


def write_config(
    tmp: Path,
    source_port: int,
    *,
    queue_max: int = 10_000,
    cot_port: int | None = None,
    airframe_link: int | None = None,
) -> Path:
    config: dict[str, Any] = {
        "gateway": {"node_id": "nffi-blue", "shutdown_deadline_s": 3},
        "health": {"host": "127.0.0.1", "port": 0},
        "airframes": [],
        "sources": [
            {
                "name": "jas_relay",
                "type": "nffi",
                "uri": f"tcp://127.0.0.1:{source_port}",
                "allow": ["127.0.0.1/32"],
            }
        ],
        "processors": [
            {
                "name": "cuas",
                "type": "counter_uas",
                "queue_max": queue_max,
                "options": {
                    "batteries": [
                        {
                            "id": "GUTE-1",
                            "lat_deg": 65.0,
                            "lon_deg": 21.0,
                            "effectors": ["TRIDON_MK2_40MM"],
                        }
                    ],
                    "blue_forces": [
                        {"uid": "SWE.HQ.U0", "callsign": "HQ", "lat_deg": 65.5, "lon_deg": 21.5}
                    ],
                },
            }
        ],
        "sinks": [{"name": "null", "type": "null"}],
        "routes": [{"sinks": ["null"]}],
    }
    if cot_port is not None:
        config["sinks"].append(
            {
                "name": "atak",
                "type": "cot",
                "options": {
                    "destinations": [f"udp://127.0.0.1:{cot_port}"],
                    "kinds": ["blue_force"],
                },
            }
        )
        config["routes"].append({"sinks": ["atak"], "kinds": ["blue_force"]})
    if airframe_link is not None:
        config["airframes"] = [
            {
                "id": "F26E-001",
                "sysid": 1,
                "links": [{"uri": f"udp://127.0.0.1:{airframe_link}", "security": "unsecured"}],
            }
        ]
        config["sinks"].append(
            {
                "name": "c2",
                "type": "nffi",
                "options": {"path": str(tmp / "nffi.xml"), "country": "SWE"},
            }
        )
        config["routes"].append({"sinks": ["c2"], "kinds": ["telemetry"]})
    path = tmp / "config.yaml"
    path.write_text(json.dumps(config))
    return path


def cuas_status(daemon: Daemon) -> dict[str, Any]:
    (processor,) = daemon.status()["processors"]
    return processor  # type: ignore[no-any-return]


def send(port: int, data: bytes) -> None:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as peer:
        peer.sendall(data)


def test_friendly_reports_lost_to_a_full_inbox_make_the_picture_incomplete(
    tmp_path: Path,
) -> None:
    port = free_tcp_port()
    with running(write_config(tmp_path, port, queue_max=50)) as daemon:
        now = datetime.now(UTC) - timedelta(seconds=1)
        send(port, friendly_reports(20, now))
        wait_until(
            lambda: cuas_status(daemon)["detail"]["blue_units"] == 21,
            20.0,
            "the first 20 units and the fixed one in the registry",
        )
        # The fixed unit is not among them, and counts as current too.
        assert cuas_status(daemon)["detail"]["blue_picture_complete"] is True
        # 500 reports in one document: published in one go, far more than the inbox holds.
        send(port, friendly_reports(500, now + timedelta(seconds=1)))

        def all_accepted() -> bool:
            (source,) = daemon.status()["sources"]
            return int(source["counts"].get("accepted", 0)) == 520

        wait_until(all_accepted, 20.0, "the source to accept all 520 reports")
        status = cuas_status(daemon)
        assert status["dropped"] > 0, status
        assert status["detail"]["blue_dropped"] == status["dropped"]
        assert status["detail"]["blue_picture_complete"] is False
        assert daemon.proc.poll() is None


def test_a_report_under_a_fixed_units_uid_reaches_no_sink(tmp_path: Path) -> None:
    port = free_tcp_port()
    cot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    cot.bind(("127.0.0.1", 0))
    cot.settimeout(0.2)
    datagrams: list[bytes] = []
    with cot, running(write_config(tmp_path, port, cot_port=cot.getsockname()[1])) as daemon:
        now = datetime.now(UTC) - timedelta(seconds=1)
        # SWE.HQ.U0 is fixed by orders at 65.5 N; the forged report moves it to 60 N. U1 is
        # an ordinary unit in the same document.
        send(port, friendly_reports(2, now, system="HQ", lat=60.0))

        def ordinary_unit_drawn() -> bool:
            with contextlib.suppress(TimeoutError):
                datagrams.append(cot.recv(65_536))
            return any(b'uid="SWE.HQ.U1"' in d for d in datagrams)

        wait_until(ordinary_unit_drawn, 20.0, "the ordinary unit on the CoT peer")
        # Sent before U1 in the same document: had it gone out, it would be here by now.
        fixed = [d for d in datagrams if b'uid="SWE.HQ.U0"' in d]
        assert fixed, "the fixed unit is announced at start"
        assert all(b'lat="65.5"' in d for d in fixed), fixed
        (source,) = daemon.status()["sources"]
        assert source["counts"]["accepted"] == 2
        assert source["pinned_refused"] == 1
        assert daemon.events("blue_force_pinned_uid_refused")[0]["uid"] == "SWE.HQ.U0"


def test_our_own_airframe_echoed_back_over_nffi_is_not_a_friendly_unit(tmp_path: Path) -> None:
    port = free_tcp_port()
    cot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    cot.bind(("127.0.0.1", 0))
    cot.settimeout(0.2)
    datagrams: list[bytes] = []
    config = write_config(
        tmp_path, port, cot_port=cot.getsockname()[1], airframe_link=free_udp_port()
    )
    with cot, running(config) as daemon:
        now = datetime.now(UTC) - timedelta(seconds=1)
        # What our nffi sink sends for F26E-001 (trackSource SWE / FISCHER-GW / F26E-001),
        # as a C2 system relaying every track it knows would send it back; then a real friend.
        echo = friendly_reports(1, now, system="FISCHER-GW", name="F26E-001")
        send(port, echo + friendly_reports(1, now, system="JAS39-RELAY", name="39-7"))

        def friend_drawn() -> bool:
            with contextlib.suppress(TimeoutError):
                datagrams.append(cot.recv(65_536))
            return any(b'uid="SWE.JAS39-RELAY.39-7"' in d for d in datagrams)

        wait_until(friend_drawn, 20.0, "the relayed friend on the CoT peer")
        assert not [d for d in datagrams if b"FISCHER-GW" in d], datagrams
        (source,) = daemon.status()["sources"]
        assert source["counts"]["accepted"] == 2
        assert source["own_refused"] == 1
        assert source["pinned_refused"] == 0
        (refused,) = daemon.events("blue_force_own_uid_refused")
        assert refused["uid"] == "SWE.FISCHER-GW.F26E-001"
