"""Terrain: DEM tiles made in the test give the interpolated values expected."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

from gateway.domain.terrain import (
    DemSource,
    HgtTile,
    TerrainError,
    TerrainModel,
    agl_from_msl,
    agl_sigma,
    safe_floor_agl_m,
)


def write_hgt(directory: Path, name: str, void_at: tuple[int, int] | None = None) -> Path:
    """A 1201² tile whose sample (row, col) is 1000 + row + 2*col metres."""
    rows, cols = np.mgrid[0:1201, 0:1201]
    grid = (1000 + rows + 2 * cols).astype(">i2")
    if void_at is not None:
        grid[void_at] = -32768
    path = directory / name
    path.write_bytes(grid.tobytes())
    return path


def test_hgt_bilinear_interpolation(tmp_path: Path) -> None:
    tile = HgtTile(write_hgt(tmp_path, "N65E021.hgt"))
    # North-west corner is row 0, col 0.
    assert tile.elevation(66.0, 21.0) == 1000.0
    # Half a sample south and east of (row 10, col 20): mean of the four neighbours.
    lat = 66.0 - 10.5 / 1200
    lon = 21.0 + 20.5 / 1200
    assert tile.elevation(lat, lon) == pytest.approx(1000 + 10.5 + 2 * 20.5)
    # A quarter of the way along a row only.
    assert tile.elevation(66.0 - 3 / 1200, 21.0 + 7.25 / 1200) == pytest.approx(1000 + 3 + 14.5)
    assert tile.elevation(65.0, 22.0) == 1000 + 1200 + 2400


def test_void_gives_none_and_the_next_source_answers(tmp_path: Path) -> None:
    fine, coarse = tmp_path / "fine", tmp_path / "coarse"
    fine.mkdir()
    coarse.mkdir()
    write_hgt(fine, "N65E021.hgt", void_at=(0, 0))
    write_hgt(coarse, "N65E021.hgt")
    model = TerrainModel(
        [
            DemSource("lantmateriet_2m", fine, "hgt", 0.5),
            DemSource("srtm_30m", coarse, "hgt", 5.0),
        ]
    )
    elevation, source = model.lookup(66.0, 21.0) or (None, None)
    assert (elevation, source.name if source else None) == (1000.0, "srtm_30m")
    elevation, source = model.lookup(65.5, 21.5) or (None, None)
    assert source is not None
    assert source.name == "lantmateriet_2m"
    assert model.ground_elevation_m(10.0, 10.0) is None


def test_geotiff_tile(tmp_path: Path) -> None:
    data = np.array([[10.0, 20.0, 30.0], [40.0, 50.0, 60.0], [70.0, 80.0, -9999.0]], np.float32)
    path = tmp_path / "tile.tif"
    tifffile.imwrite(
        path,
        data,
        extratags=[
            (33550, "d", 3, (0.001, 0.001, 0.0)),  # ModelPixelScale: 0.001° per sample
            (33922, "d", 6, (0.0, 0.0, 0.0, 21.0, 66.0, 0.0)),  # tie: (0,0) at 21 E 66 N
            (42113, "s", 0, "-9999"),  # GDAL_NODATA
        ],
    )
    model = TerrainModel([DemSource("lantmateriet_2m", tmp_path, "geotiff", 0.5)])
    assert model.ground_elevation_m(66.0, 21.0) == pytest.approx(10.0)
    assert model.ground_elevation_m(65.9995, 21.0005) == pytest.approx(30.0)
    assert model.ground_elevation_m(65.9985, 21.0015) is None  # touches the no-data sample
    assert model.ground_elevation_m(65.0, 21.0) is None


def test_bad_tile_names_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "N65E021.hgt"
    bad.write_bytes(b"\x00" * 100)
    with pytest.raises(TerrainError, match=r"N65E021\.hgt"):
        HgtTile(bad)


def test_agl_sigma_and_safety_floor() -> None:
    sigma = agl_sigma(0.5, 5.0)
    assert sigma == pytest.approx(5.0249, abs=1e-4)
    assert safe_floor_agl_m(sigma, clearance_m=30.0) == pytest.approx(30 + 3 * sigma)
    assert agl_from_msl(250.0, 180.0) == 70.0


def test_telemetry_gains_agl_and_endurance(tmp_path: Path) -> None:
    """Through ingest: AGL where the DEM covers the airframe, endurance from the battery."""
    from datetime import UTC, datetime

    from pymavlink.dialects.v20 import ardupilotmega as mav

    from gateway.config import AirframeConfig, LinkConfig
    from gateway.events import Event, Telemetry
    from gateway.ingest import Ingest, LinkIntake
    from gateway.instruments import Instruments

    write_hgt(tmp_path, "N65E021.hgt")
    events: list[Event] = []
    airframe = AirframeConfig(
        id="A",
        sysid=1,
        links=(LinkConfig(uri="udp://127.0.0.1:1", name="l", security="unsecured"),),
        ew_mode="heavy",
    )
    terrain = TerrainModel([DemSource("srtm_30m", tmp_path, "hgt", 5.0)])
    ingest = Ingest(
        [airframe],
        events.append,
        Instruments(),
        lambda: datetime(2026, 11, 22, tzinfo=UTC),
        terrain=terrain,
        baro_sigma_m=0.5,
    )
    ingest.register_link(LinkIntake("l", "unsecured", is_stream=False))
    m = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    # 66.0 N 21.0 E is the tile's north-west sample: ground 1000 m.
    position = m.global_position_int_encode(0, 660000000, 210000000, 1250000, 0, 0, 0, 0, 0)
    ingest.on_data("l", "p", bytes(position.pack(m)))
    status = m.sys_status_encode(0, 0, 0, 0, 22000, 1000, 50, 0, 0, 0, 0, 0, 0)
    ingest.on_data("l", "p", bytes(status.pack(m)))
    telemetry = [e for e in events if isinstance(e, Telemetry)][-1]
    assert telemetry.alt_agl_m == pytest.approx(250.0)
    assert telemetry.agl_sigma_m == pytest.approx(agl_sigma(0.5, 5.0))
    # Half of the 800 Wh pack at 355 W + 125 W (heavy EW), no sun: 50 minutes.
    assert telemetry.endurance_remaining_min == pytest.approx(50.0)
    assert telemetry.ew_mode == "heavy"
