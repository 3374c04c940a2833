"""Processor ``counter_uas``: options as config, fixed friends announced, tracks to handoffs."""

from __future__ import annotations

import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import anyio
import pytest

from gateway.domain.geodesy import destination
from gateway.domain.peertext import Provenance
from gateway.events import BlueForce, Event, Handoff, Position, Track
from processors.counter_uas import CounterUasConfig, CounterUasProcessor

OPTIONS = {
    "batteries": [
        {
            "id": "GUTE-1",
            "lat_deg": 65.80,
            "lon_deg": 21.70,
            "effectors": ["TRACKFIRE_30MM", "TRIDON_MK2_40MM", "EW_COUNTERMEASURES"],
        }
    ],
    "blue_forces": [{"uid": "PLT-1", "callsign": "1. pluton", "lat_deg": 65.79, "lon_deg": 21.6}],
}


def track(track_id: str, bearing: float, distance_m: float, status: str = "created") -> Track:
    # The time of the call, not of the import: a suite longer than the processor's
    # blue_max_age_s would otherwise hand it friends that are already too old to count.
    now = datetime.now(UTC)
    lat, lon = destination(65.80, 21.70, bearing, distance_m)
    return Track.model_validate(
        {
            "event_id": f"{track_id}-1",
            "track_id": track_id,
            "time": now,
            "status": status,
            "object_class": "loitering_munition",
            "confidence": 0.95,
            "position": {"lat_deg": lat, "lon_deg": lon},
            "cep50_m": 10.0,
            "cep90_m": 18.0,
            "first_seen": now,
            "last_seen": now,
        }
    )


@pytest.mark.anyio
async def test_fixed_friends_are_announced_and_each_track_is_handed_off_once() -> None:
    processor = CounterUasProcessor("cuas", CounterUasConfig.model_validate(OPTIONS))
    published: list[Event] = []
    send, receive = anyio.create_memory_object_stream[Event](100)
    async with anyio.create_task_group() as tg:
        await tg.start(processor.run, receive, published.append)
        # A friend reported next to the second track's position.
        lat, lon = destination(65.80, 21.70, 270, 2000)
        lat, lon = destination(lat, lon, 0, 150)
        await send.send(
            BlueForce(
                event_id="b1",
                uid="ANDROID-7",
                time=datetime.now(UTC),
                callsign="Alfa 7",
                position=Position(lat_deg=lat, lon_deg=lon),
                source="cot",
            )
        )
        for event in (
            track("T-1", 90, 2000),
            track("T-1", 90, 1900, "updated"),
            track("T-2", 270, 2000),
        ):
            await send.send(event)
        send.close()
    assert isinstance(published[0], BlueForce)
    assert published[0].uid == "PLT-1"
    assert published[0].source == "config:cuas"
    assert (published[0].source_name, published[0].provenance) == ("cuas", Provenance.CONFIGURED)
    handoffs = [e for e in published if isinstance(e, Handoff)]
    assert [h.track.track_id for h in handoffs] == ["T-1", "T-2"]
    assert handoffs[0].deconfliction.clear
    assert handoffs[0].recommended_effector == "TRACKFIRE_30MM"
    assert not handoffs[1].deconfliction.clear
    assert handoffs[1].deconfliction.nearest_blue_callsign == "Alfa 7"
    assert handoffs[1].recommended_effector is None
    assert processor.status()["handed_off"] == 2


def test_bad_options_are_named_by_check_config(tmp_path: Path) -> None:
    config = tmp_path / "node.yaml"
    config.write_text(
        "processors:\n"
        "  - name: cuas\n"
        "    type: counter_uas\n"
        "    options:\n"
        "      batteries:\n"
        "        - id: GUTE-1\n"
        "          lat_deg: 95\n"
        "          lon_deg: 21.7\n"
        "          effectors: [TRACKFIRE_30MM]\n"
        "  - name: cuas2\n"
        "    type: counter_uas\n"
        "    options:\n"
        "      batteries:\n"
        "        - {id: GUTE-2, lat_deg: 65, lon_deg: 21, effectors: [RAILGUN]}\n"
    )
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", "--no-environment", str(config)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 2, result.stdout + result.stderr
    out = result.stdout + result.stderr
    assert "processors[0].options.batteries[0].lat_deg" in out
    assert "node.yaml:7 processors[0].options.batteries[0].lat_deg" in out
    assert "RAILGUN" in out
