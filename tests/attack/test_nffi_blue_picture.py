"""An NFFI peer against the blue-force picture, through ``fischer-gateway run --config FILE``.

A flood of friendly reports larger than the ``counter_uas`` processor's inbox: the reports it
never got may have held a real unit's newest position, so the picture must then say it is
incomplete (cues never "clear"), not silently keep deconflicting against what is left.
"""

from __future__ import annotations

import json
import socket
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Daemon, free_tcp_port, running, wait_until

from gateway.codecs.nffi import NffiOptions, encode_message, tracks_of
from gateway.events import BlueForce, Position

pytestmark = pytest.mark.timeout(120)


def friendly_reports(count: int, at: datetime) -> bytes:
    """One NFFI document with ``count`` distinct friendly ground units."""
    units = [
        BlueForce(
            event_id="-",
            uid=f"U{n}",
            time=at,
            position=Position(lat_deg=65.0 + n * 1e-4, lon_deg=21.0),
            source="-",
        )
        for n in range(count)
    ]
    return encode_message(tracks_of(units, NffiOptions(system="FLOOD", country="SWE")))


def write_config(tmp: Path, source_port: int, *, queue_max: int) -> Path:
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
                },
            }
        ],
        "sinks": [{"name": "null", "type": "null"}],
        "routes": [{"sinks": ["null"]}],
    }
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
            lambda: cuas_status(daemon)["detail"]["blue_units"] == 20,
            20.0,
            "the first 20 units in the registry",
        )
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
