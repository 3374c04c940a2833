"""Terrain: DEM tiles made in the test give the interpolated values worked out by hand."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
from structlog.testing import capture_logs

from gateway.domain.dem import HgtTile, TerrainError, read_geotiff_header
from gateway.domain.terrain import (
    DemSource,
    TerrainModel,
    agl_from_msl,
    agl_sigma,
    check_sources,
    msl_from_agl,
    safe_floor_agl_m,
    safe_floor_msl_m,
)

STEP = 1 / 1200  # a 3″ SRTM tile: 1201 samples a side, 1200 steps per degree


def write_hgt(
    directory: Path, name: str = "N65E021.hgt", size: int = 1201, base: int = 1000
) -> Path:
    """A tile whose sample (row, col) is base + row + 2·col metres, plus one hand-made cell:
    rows 100–101, cols 200–201 hold 10, 20 (north) and 30, 50 (south)."""
    grid = (base + np.arange(size)[:, None] + 2 * np.arange(size)[None, :]).astype(">i2")
    grid[100:102, 200:202] = [[10, 20], [30, 50]]
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / name
    path.write_bytes(grid.tobytes())
    return path


def hgt_point(
    row: float, col: float, south: float = 65.0, west: float = 21.0
) -> tuple[float, float]:
    return south + 1 - row * STEP, west + col * STEP


class TestHgt:
    """SRTM .hgt tiles: layout, bilinear interpolation and voids."""

    def test_samples_are_read_where_srtm_puts_them(self, tmp_path: Path) -> None:
        tile = HgtTile(write_hgt(tmp_path))
        assert tile.elevation(66.0, 21.0) == 1000.0  # row 0, col 0 is the north-west corner
        assert tile.elevation(65.0, 21.0) == 1000 + 1200  # south-west
        assert tile.elevation(66.0, 22.0) == 1000 + 2400  # north-east
        assert tile.elevation(65.0, 22.0) == 1000 + 1200 + 2400  # south-east
        assert tile.elevation(*hgt_point(7, 9)) == pytest.approx(1000 + 7 + 18, abs=1e-6)

    def test_bilinear_interpolation_inside_a_cell(self, tmp_path: Path) -> None:
        """Corners 10, 20 / 30, 50; a quarter down and half across: 15 → 40 → 21.25."""
        tile = HgtTile(write_hgt(tmp_path))
        assert tile.elevation(*hgt_point(100.25, 200.5)) == pytest.approx(21.25, abs=1e-6)
        assert tile.elevation(*hgt_point(100.5, 200.5)) == pytest.approx(27.5, abs=1e-6)
        assert tile.elevation(*hgt_point(101.0, 200.75)) == pytest.approx(45.0, abs=1e-6)
        # On a plane (the rest of the tile) bilinear is exact at any point.
        assert tile.elevation(*hgt_point(10.3, 20.6)) == pytest.approx(1000 + 10.3 + 41.2, abs=1e-6)

    def test_one_arc_second_tiles(self, tmp_path: Path) -> None:
        tile = HgtTile(write_hgt(tmp_path, size=3601))
        assert tile.geometry.rows == 3601
        lat, lon = 66.0 - 2.5 / 3600, 21.0 + 4.5 / 3600
        assert tile.elevation(lat, lon) == pytest.approx(1000 + 2.5 + 9.0, abs=1e-6)

    def test_a_void_gives_none_unless_it_has_no_weight(self, tmp_path: Path) -> None:
        path = write_hgt(tmp_path)
        grid = np.frombuffer(path.read_bytes(), ">i2").reshape(1201, 1201).copy()
        grid[10, 10] = -32768
        path.write_bytes(grid.tobytes())
        tile = HgtTile(path)
        assert tile.elevation(*hgt_point(10.5, 10.5)) is None
        assert tile.elevation(*hgt_point(10, 10)) is None
        # On the neighbouring sample the void has zero weight and must not hide the value.
        assert tile.elevation(*hgt_point(10, 11)) == pytest.approx(1000 + 10 + 22, abs=1e-6)

    def test_a_tile_of_the_wrong_size_or_name_is_refused(self, tmp_path: Path) -> None:
        bad = tmp_path / "N65E021.hgt"
        bad.write_bytes(b"\x00" * 100)
        with pytest.raises(TerrainError, match=r"N65E021\.hgt: 100 bytes"):
            HgtTile(bad)
        with pytest.raises(TerrainError, match="expected a name like"):
            HgtTile(write_hgt(tmp_path, "dem.hgt"))

    def test_southern_and_western_tiles(self, tmp_path: Path) -> None:
        tile = HgtTile(write_hgt(tmp_path, "S34W071.hgt"))
        assert tile.elevation(-33.0, -71.0) == 1000.0
        assert tile.elevation(-34.0, -70.0) == 1000 + 1200 + 2400


def geokeys(epsg: int, *, projected: bool, pixel_is_point: bool = False) -> tuple[int, ...]:
    """A GeoKeyDirectory: model type, raster type and the EPSG code of the CRS."""
    crs_key = 3072 if projected else 2048
    raster = 2 if pixel_is_point else 1
    return (1, 1, 0, 3, 1024, 0, 1, 1 if projected else 2, 1025, 0, 1, raster, crs_key, 0, 1, epsg)


def write_geotiff(
    path: Path,
    data: np.ndarray,
    *,
    scale: tuple[float, float],
    tie: tuple[float, float],
    keys: tuple[int, ...] | None,
    nodata: str | None = None,
    compression: str | None = None,
) -> Path:
    tags: list[tuple[int, str, int, object]] = [
        (33550, "d", 3, (scale[0], scale[1], 0.0)),  # ModelPixelScale
        (33922, "d", 6, (0.0, 0.0, 0.0, tie[0], tie[1], 0.0)),  # raster (0, 0) → model (x, y)
    ]
    if keys is not None:
        tags.append((34735, "H", len(keys), keys))
    if nodata is not None:
        tags.append((42113, "s", 0, nodata))  # GDAL_NODATA
    path.parent.mkdir(parents=True, exist_ok=True)
    tifffile.imwrite(path, data, extratags=tags, compression=compression)
    return path


def lantmateriet_tile(directory: Path, *, compression: str | None = "lzw") -> Path:
    """An 8×8 sample, 2 m, pixel-is-area SWEREF 99 TM tile around Linköping, like
    Lantmäteriet's grid 2+ (LZW). Sample (r, c) is at E 536301 + 2c, N 6474619 − 2r
    (pixel centres) and holds 100 + 3r + 2c metres."""
    rows, cols = np.mgrid[0:8, 0:8]
    data = (100 + 3 * rows + 2 * cols).astype(np.float32)
    data[7, 7] = -9999.0
    return write_geotiff(
        directory / "64_53_2025.tif",
        data,
        scale=(2.0, 2.0),
        tie=(536300.0, 6474620.0),  # the north-west corner of the north-west pixel
        keys=geokeys(3006, projected=True),
        nodata="-9999",
        compression=compression,
    )


class TestGeoTiff:
    """GeoTIFF tiles: SWEREF 99 TM pixel-is-area (Lantmäteriet) and geographic pixel-is-point."""

    # Linköping, 58.4108 N 15.6214 E, is E 536308.536 N 6474614.999 in SWEREF 99 TM (pyproj):
    # row (6474619 − 6474614.999) / 2 = 2.0005, col (536308.536 − 536301) / 2 = 3.768.
    LINKOPING_M = 100 + 3 * 2.0005 + 2 * 3.768

    @pytest.mark.parametrize("compression", ["lzw", "zlib", None])
    def test_sweref99_tm_tile(self, tmp_path: Path, compression: str | None) -> None:
        lantmateriet_tile(tmp_path, compression=compression)
        model = TerrainModel([DemSource("lantmateriet_2m", tmp_path, "geotiff", 0.5)])
        ground = model.ground_elevation_m(58.4108, 15.6214)
        assert ground == pytest.approx(self.LINKOPING_M, abs=0.005)

    def test_pixel_is_area_header(self, tmp_path: Path) -> None:
        header = read_geotiff_header(lantmateriet_tile(tmp_path))
        g = header.geometry
        assert (g.x0, g.y0, g.dx, g.dy, g.rows, g.cols) == (536301, 6474619, 2, 2, 8, 8)
        assert g.bounds() == (536300, 6474604, 536316, 6474620)  # the pixels' outer edges
        assert (g.crs.epsg, header.nodata) == (3006, -9999.0)

    def test_geographic_pixel_is_point_tile(self, tmp_path: Path) -> None:
        data = np.array([[10.0, 20.0, 30.0], [40.0, 50.0, 60.0], [70.0, 80.0, -9999.0]])
        write_geotiff(
            tmp_path / "tile.tif",
            data.astype(np.float32),
            scale=(0.001, 0.001),
            tie=(21.0, 66.0),  # sample (0, 0) itself is at 21 E 66 N
            keys=geokeys(4326, projected=False, pixel_is_point=True),
            nodata="-9999",
            compression="zlib",
        )
        model = TerrainModel([DemSource("grid", tmp_path, "geotiff", 1.0)])
        assert model.ground_elevation_m(66.0, 21.0) == pytest.approx(10.0)
        assert model.ground_elevation_m(65.9995, 21.0005) == pytest.approx(30.0)  # 10 20 40 50
        assert model.ground_elevation_m(65.99925, 21.0015) == pytest.approx(47.5)  # 20 30 50 60
        assert model.ground_elevation_m(65.9985, 21.0015) is None  # needs the no-data sample
        assert model.ground_elevation_m(65.0, 21.0) is None  # outside

    def test_a_geotiff_without_geokeys_is_refused(self, tmp_path: Path) -> None:
        write_geotiff(
            tmp_path / "bare.tif", np.zeros((4, 4), np.float32), scale=(1, 1), tie=(0, 0), keys=None
        )
        with pytest.raises(TerrainError, match=r"bare\.tif: no GeoKeyDirectory"):
            TerrainModel([DemSource("grid", tmp_path, "geotiff", 1.0)])

    def test_an_unsupported_crs_is_named(self, tmp_path: Path) -> None:
        write_geotiff(
            tmp_path / "merc.tif",
            np.zeros((4, 4), np.float32),
            scale=(1, 1),
            tie=(0, 0),
            keys=geokeys(3857, projected=True),
        )
        with pytest.raises(TerrainError, match=r"merc\.tif: EPSG:3857 is not supported"):
            TerrainModel([DemSource("grid", tmp_path, "geotiff", 1.0)])


class TestTerrainModel:
    """Source order, the tile index and the cache."""

    def test_the_first_source_with_data_answers(self, tmp_path: Path) -> None:
        lantmateriet_tile(tmp_path / "lm")
        write_hgt(tmp_path / "srtm", "N58E015.hgt", base=200)
        model = TerrainModel(
            [
                DemSource("lantmateriet_2m", tmp_path / "lm", "geotiff", 0.5),
                DemSource("srtm_30m", tmp_path / "srtm", "hgt", 5.0),
            ]
        )
        ground, source = model.lookup(58.4108, 15.6214) or (None, None)
        assert source is not None
        assert (ground, source.name) == (
            pytest.approx(TestGeoTiff.LINKOPING_M, abs=0.005),
            "lantmateriet_2m",
        )
        # Outside the 16 m Lantmäteriet tile, SRTM answers.
        ground, source = model.lookup(58.5, 15.5) or (None, None)
        assert source is not None
        assert (ground, source.name) == (pytest.approx(200 + 600 + 1200, abs=1e-6), "srtm_30m")
        assert model.ground_elevation_m(10.0, 10.0) is None

    def test_a_void_falls_through_to_the_next_source(self, tmp_path: Path) -> None:
        fine = write_hgt(tmp_path / "fine")
        grid = np.frombuffer(fine.read_bytes(), ">i2").reshape(1201, 1201).copy()
        grid[0, 0] = -32768
        fine.write_bytes(grid.tobytes())
        write_hgt(tmp_path / "coarse", base=500)
        model = TerrainModel(
            [
                DemSource("fine", tmp_path / "fine", "hgt", 1.0),
                DemSource("coarse", tmp_path / "coarse", "hgt", 5.0),
            ]
        )
        found = model.lookup(66.0, 21.0)
        assert found is not None
        assert (found[0], found[1].name) == (500.0, "coarse")
        found = model.lookup(65.5, 21.5)
        assert found is not None
        assert found[1].name == "fine"

    def test_a_point_on_a_shared_edge_is_answered_by_either_tile(self, tmp_path: Path) -> None:
        """66° N is N65E021's north row and N66E021's south row; either tile alone answers."""
        write_hgt(tmp_path / "south")
        write_hgt(tmp_path / "north", "N66E021.hgt", base=-200)
        south = TerrainModel([DemSource("srtm", tmp_path / "south", "hgt", 5.0)])
        north = TerrainModel([DemSource("srtm", tmp_path / "north", "hgt", 5.0)])
        assert south.ground_elevation_m(66.0, 21.5) == pytest.approx(1000 + 1200, abs=1e-6)
        assert north.ground_elevation_m(66.0, 21.5) == pytest.approx(-200 + 1200 + 1200, abs=1e-6)

    def test_only_the_tile_covering_the_point_is_loaded(self, tmp_path: Path) -> None:
        for lat in range(60, 66):
            for lon in range(14, 20):
                write_hgt(tmp_path, f"N{lat:02d}E{lon:03d}.hgt")
        model = TerrainModel([DemSource("srtm", tmp_path, "hgt", 5.0)], cache_tiles=2)
        assert model.ground_elevation_m(63.5, 17.5) is not None
        assert model.cached_paths == (tmp_path / "N63E017.hgt",)
        model.ground_elevation_m(61.5, 15.5)
        model.ground_elevation_m(62.5, 16.5)
        assert model.cached_paths == (tmp_path / "N61E015.hgt", tmp_path / "N62E016.hgt")
        model.close()
        assert model.cached_paths == ()

    def test_the_cache_is_bounded_in_bytes(self, tmp_path: Path) -> None:
        write_hgt(tmp_path, "N60E014.hgt")
        write_hgt(tmp_path, "N60E015.hgt")
        model = TerrainModel([DemSource("srtm", tmp_path, "hgt", 5.0)], cache_bytes=3_000_000)
        model.ground_elevation_m(60.5, 14.5)
        model.ground_elevation_m(60.5, 15.5)
        assert model.cached_paths == (tmp_path / "N60E015.hgt",)  # 2.9 MB each: room for one

    def test_every_unusable_tile_is_listed_at_construction(self, tmp_path: Path) -> None:
        (tmp_path / "N60E014.hgt").write_bytes(b"\x00" * 10)
        (tmp_path / "N60E015.hgt").write_bytes(b"\x00" * 12)
        with pytest.raises(TerrainError, match=r"(?s)N60E014\.hgt: 10 bytes.*N60E015\.hgt: 12"):
            TerrainModel([DemSource("srtm", tmp_path, "hgt", 5.0)])

    def test_a_missing_directory_is_an_error(self, tmp_path: Path) -> None:
        with pytest.raises(TerrainError, match="'srtm' is not a directory"):
            TerrainModel([DemSource("srtm", tmp_path / "absent", "hgt", 5.0)])

    def test_a_tile_broken_after_indexing_is_skipped_and_logged(self, tmp_path: Path) -> None:
        path = write_hgt(tmp_path / "fine")
        write_hgt(tmp_path / "coarse", base=500)
        model = TerrainModel(
            [
                DemSource("fine", tmp_path / "fine", "hgt", 1.0),
                DemSource("coarse", tmp_path / "coarse", "hgt", 5.0),
            ]
        )
        path.write_bytes(b"\x00" * 10)  # truncated after the daemon started
        with capture_logs() as logs:
            assert model.ground_elevation_m(66.0, 21.0) == 500.0
            assert model.ground_elevation_m(66.0, 21.0) == 500.0
        # Logged once; its only tile gone, the source is disabled.
        assert [e["event"] for e in logs] == ["dem_tile_skipped", "dem_source_disabled"]
        assert logs[0]["path"] == str(path)
        assert not model.is_source_up("fine")
        assert model.is_source_up("coarse")

    @pytest.mark.parametrize(("lat", "lon"), [(float("nan"), 21.0), (95.0, 21.0), (66.0, 200.0)])
    def test_impossible_positions_have_no_ground(
        self, tmp_path: Path, lat: float, lon: float
    ) -> None:
        write_hgt(tmp_path)
        model = TerrainModel([DemSource("srtm", tmp_path, "hgt", 5.0)])
        assert model.ground_elevation_m(lat, lon) is None

    def test_agl_estimate(self, tmp_path: Path) -> None:
        write_hgt(tmp_path)
        model = TerrainModel([DemSource("srtm_30m", tmp_path, "hgt", 5.0)])
        estimate = model.agl(66.0, 21.0, alt_msl_m=1250.0, baro_sigma_m=0.5)
        assert estimate is not None
        assert (estimate.alt_agl_m, estimate.ground_msl_m, estimate.source) == (
            250.0,
            1000.0,
            "srtm_30m",
        )
        assert estimate.sigma_m == pytest.approx(5.0249378, abs=1e-7)
        assert model.agl(10.0, 10.0, 100.0, 0.5) is None


def test_agl_sigma_and_safety_floors() -> None:
    sigma = agl_sigma(0.5, 5.0)
    assert sigma == pytest.approx(5.0249378, abs=1e-7)  # √25.25
    assert safe_floor_agl_m(sigma, clearance_m=30.0) == pytest.approx(30 + 3 * sigma)
    assert safe_floor_msl_m(180.0, 2.0, clearance_m=30.0) == 216.0
    assert agl_from_msl(250.0, 180.0) == 70.0
    assert msl_from_agl(70.0, 180.0) == 250.0
    with pytest.raises(ValueError, match="must not be negative"):
        safe_floor_agl_m(-1.0)


def corrupt_geotiff(directory: Path) -> Path:
    """A Lantmäteriet-like tile whose header reads but whose LZW data is garbage."""
    path = lantmateriet_tile(directory)
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        spans = list(zip(page.dataoffsets, page.databytecounts, strict=True))
    raw = bytearray(path.read_bytes())
    for offset, count in spans:
        raw[offset : offset + count] = b"\xff" * count
    path.write_bytes(bytes(raw))
    return path


class TestDegradedTerrain:
    """A failing DEM source never stops a lookup: it is skipped or disabled, and counted."""

    def test_an_undecodable_tile_is_skipped_and_the_next_source_answers(
        self, tmp_path: Path
    ) -> None:
        """imagecodecs raises its own RuntimeError subclass on corrupt LZW data."""
        corrupt_geotiff(tmp_path / "lm")
        write_hgt(tmp_path / "srtm", "N58E015.hgt", base=200)
        model = TerrainModel(
            [
                DemSource("lantmateriet_2m", tmp_path / "lm", "geotiff", 0.5),
                DemSource("srtm_30m", tmp_path / "srtm", "hgt", 5.0),
            ]
        )
        with capture_logs() as logs:
            for _ in range(3):
                found = model.lookup(58.4108, 15.6214)
                assert found is not None
                assert found[1].name == "srtm_30m"
        assert [e["event"] for e in logs] == ["dem_tile_skipped", "dem_source_disabled"]
        assert "ImcdError" in logs[0]["error"]
        assert model.errors == {("lantmateriet_2m", "undecodable"): 1}
        states = {s["source"]: (s["state"], s["tiles_skipped"]) for s in model.status()}
        assert states == {"lantmateriet_2m": ("disabled", 1), "srtm_30m": ("up", 0)}

    def test_a_source_whose_every_tile_is_unreadable_is_disabled_at_start(
        self, tmp_path: Path
    ) -> None:
        (tmp_path / "lm").mkdir()
        (tmp_path / "lm" / "x.tif").write_bytes(b"not a tiff at all")
        write_hgt(tmp_path / "srtm")
        with capture_logs() as logs:
            model = TerrainModel(
                [
                    DemSource("lantmateriet_2m", tmp_path / "lm", "geotiff", 0.5),
                    DemSource("srtm_30m", tmp_path / "srtm", "hgt", 5.0),
                ],
                strict=False,  # as the daemon builds it
            )
        assert "dem_source_disabled" in [e["event"] for e in logs]
        states = {s["source"]: s["state"] for s in model.status()}
        assert states == {"lantmateriet_2m": "disabled", "srtm_30m": "up"}

    def test_a_missing_directory_disables_only_that_source(self, tmp_path: Path) -> None:
        write_hgt(tmp_path / "srtm")
        with capture_logs() as logs:
            model = TerrainModel(
                [
                    DemSource("lantmateriet_2m", tmp_path / "absent", "hgt", 0.5),
                    DemSource("srtm_30m", tmp_path / "srtm", "hgt", 5.0),
                ],
                strict=False,
            )
        assert model.ground_elevation_m(66.0, 21.0) == 1000.0
        assert not model.is_source_up("lantmateriet_2m")
        assert model.errors == {("lantmateriet_2m", "missing"): 1}
        assert {e["event"] for e in logs} == {"dem_error", "dem_source_disabled"}
        assert model.status()[0]["reason"].endswith("is not a directory")

    def test_unreadable_tiles_are_skipped_at_start_when_not_strict(self, tmp_path: Path) -> None:
        write_hgt(tmp_path)
        (tmp_path / "N60E014.hgt").write_bytes(b"\x00" * 10)
        model = TerrainModel([DemSource("srtm", tmp_path, "hgt", 5.0)], strict=False)
        assert model.ground_elevation_m(66.0, 21.0) == 1000.0
        assert model.errors == {("srtm", "unreadable"): 1}
        assert model.status()[0]["tiles"] == 1
        assert model.status()[0]["tiles_skipped"] == 1

    def test_a_geotiff_source_without_tifffile_is_disabled(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        lantmateriet_tile(tmp_path / "lm")
        write_hgt(tmp_path / "srtm", "N58E015.hgt", base=200)
        monkeypatch.setitem(sys.modules, "tifffile", None)  # import tifffile → ImportError
        model = TerrainModel(
            [
                DemSource("lantmateriet_2m", tmp_path / "lm", "geotiff", 0.5),
                DemSource("srtm_30m", tmp_path / "srtm", "hgt", 5.0),
            ],
            strict=False,
        )
        found = model.lookup(58.4108, 15.6214)
        assert found is not None
        assert found[1].name == "srtm_30m"
        assert model.errors == {("lantmateriet_2m", "no_tifffile"): 1}
        assert "fischer-gateway[terrain]" in str(model.status()[0]["reason"])


class TestCheckSources:
    """check_sources: what check-config warns about, without opening a tile."""

    def test_good_sources_have_no_problems(self, tmp_path: Path) -> None:
        write_hgt(tmp_path / "srtm")
        lantmateriet_tile(tmp_path / "lm")
        sources = [
            DemSource("lm", tmp_path / "lm", "geotiff", 0.5),
            DemSource("srtm", tmp_path / "srtm", "hgt", 5.0),
        ]
        assert check_sources(sources) == []

    def test_each_problem_names_its_source(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        (tmp_path / "empty").mkdir()
        monkeypatch.setitem(sys.modules, "tifffile", None)
        problems = check_sources(
            [
                DemSource("lm", tmp_path / "absent", "geotiff", 0.5),
                DemSource("srtm", tmp_path / "empty", "hgt", 5.0),
            ]
        )
        assert [index for index, _ in problems] == [0, 0, 1]
        assert "tifffile" in problems[0][1]
        assert "'lm'" in problems[0][1]
        assert "is not a directory" in problems[1][1]
        assert "no .hgt tiles" in problems[2][1]
