"""Telemetry gains AGL (where a DEM covers the airframe) and predicted endurance, via ingest."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.config import AirframeConfig, LinkConfig
from gateway.domain.terrain import DemSource, TerrainModel, agl_sigma
from gateway.events import Event, Telemetry
from gateway.fleet.ingest import Ingest, LinkIntake
from gateway.ops.instruments import Instruments


def telemetry_after(tmp_path: Path, lat_e7: int, lon_e7: int) -> Telemetry:
    """Feed one position (1250 m MSL) and a half-full battery; return the last telemetry."""
    grid = np.full((1201, 1201), 1000, dtype=">i2")  # flat ground at 1000 m
    (tmp_path / "N65E021.hgt").write_bytes(grid.tobytes())
    events: list[Event] = []
    airframe = AirframeConfig(
        id="A",
        sysid=1,
        links=(LinkConfig(uri="udp://127.0.0.1:1", name="l", security="unsecured"),),
        ew_mode="heavy",
    )
    ingest = Ingest(
        [airframe],
        events.append,
        Instruments(),
        lambda: datetime(2026, 11, 22, tzinfo=UTC),
        terrain=TerrainModel([DemSource("srtm_30m", tmp_path, "hgt", 5.0)]),
        baro_sigma_m=0.5,
    )
    ingest.register_link(LinkIntake("l", "unsecured", is_stream=False))
    m = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    position = m.global_position_int_encode(0, lat_e7, lon_e7, 1_250_000, 0, 0, 0, 0, 0)
    ingest.on_data("l", "p", bytes(position.pack(m)))
    status = m.sys_status_encode(0, 0, 0, 0, 22000, 1000, 50, 0, 0, 0, 0, 0, 0)
    ingest.on_data("l", "p", bytes(status.pack(m)))
    return [e for e in events if isinstance(e, Telemetry)][-1]


def test_telemetry_gains_agl_and_endurance(tmp_path: Path) -> None:
    telemetry = telemetry_after(tmp_path, 655_000_000, 215_000_000)
    assert telemetry.alt_agl_m == pytest.approx(250.0)
    assert telemetry.agl_sigma_m == pytest.approx(agl_sigma(0.5, 5.0))
    # Half of the 800 Wh pack at 355 W + 125 W (heavy EW), no sun: 50 minutes.
    assert telemetry.endurance_remaining_min == pytest.approx(50.0)
    assert telemetry.ew_mode == "heavy"


def test_no_dem_no_agl(tmp_path: Path) -> None:
    telemetry = telemetry_after(tmp_path, 595_000_000, 185_000_000)  # no tile there
    assert telemetry.alt_agl_m is None
    assert telemetry.agl_sigma_m is None
    assert telemetry.endurance_remaining_min == pytest.approx(50.0)


def test_an_undecodable_dem_tile_costs_agl_not_telemetry(tmp_path: Path) -> None:
    """Every position becomes telemetry (without AGL) although the only tile is corrupt.

    The decoder's error used to escape ``Ingest.flush`` on every snapshot over the tile.
    """
    from test_domain_terrain import corrupt_geotiff  # same directory, imported by pytest

    corrupt_geotiff(tmp_path)
    events: list[Event] = []
    airframe = AirframeConfig(
        id="A",
        sysid=1,
        links=(LinkConfig(uri="udp://127.0.0.1:1", name="l", security="unsecured"),),
    )
    ingest = Ingest(
        [airframe],
        events.append,
        Instruments(),
        lambda: datetime(2026, 11, 22, tzinfo=UTC),
        terrain=TerrainModel([DemSource("lantmateriet_2m", tmp_path, "geotiff", 0.5)]),
    )
    ingest.register_link(LinkIntake("l", "unsecured", is_stream=False))
    m = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    for i in range(20):  # Linköping, inside the tile, moving a little each time
        lat_e7, lon_e7 = 584_108_000 + i, 156_214_000 + i
        msg = m.global_position_int_encode(i, lat_e7, lon_e7, 150_000, 0, 0, 0, 0, 0)
        ingest.on_data("l", "p", bytes(msg.pack(m)))
    telemetry = [e for e in events if isinstance(e, Telemetry)]
    assert len(telemetry) == 20
    assert all(t.position is not None and t.alt_agl_m is None for t in telemetry)
