"""DEM tile readers: SRTM ``.hgt`` and GeoTIFF grids, with bilinear interpolation.

A tile is a regular grid of elevation samples with a geometry (``GridGeometry``): the
coordinates of its first sample, the spacing, and the projection its coordinates are in.
Reading a tile's header is cheap and done once, when the terrain index is built; the samples
are read only when a lookup needs them (``HgtTile`` memory-maps the file, ``GeoTiffTile``
decodes it into an array).

- SRTM ``.hgt``: big-endian int16, 1201² (3″) or 3601² (1″) samples, −32768 = void, named
  after the south-west corner of its 1°×1° cell (``N65E021.hgt``). Samples lie *on* the
  cell edges, so neighbouring tiles share their border rows; heights are EGM96 metres.
- GeoTIFF: one band, north-up, located by the ModelPixelScale and ModelTiepoint tags, in a
  CRS from ``projection.crs_from_epsg`` (Lantmäteriet: SWEREF 99 TM, LZW-compressed).
  Pixel-is-area rasters (the GeoTIFF default, and what GDAL writes) put the sample at the
  centre of each pixel; pixel-is-point rasters at the tie point itself.
"""

from __future__ import annotations

import math
import mmap
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gateway.domain.projection import (
    GEOGRAPHIC,
    Geographic,
    ProjectionError,
    TransverseMercator,
    crs_from_epsg,
)
from gateway.errors import GatewayError

__all__ = [
    "DemTile",
    "GeoTiffHeader",
    "GeoTiffTile",
    "GridGeometry",
    "HgtTile",
    "TerrainError",
    "hgt_geometry",
    "read_geotiff_header",
]

_HGT_NAME = re.compile(r"^([NS])(\d{2})([EW])(\d{3})(?:\.[^.]+)?\.hgt$", re.IGNORECASE)
_HGT_VOID = -32768
# Weights below this (a point within a millionth of a cell of the other samples, under 0.1 mm
# on SRTM) are rounding noise, not a reason to let a void neighbour blank the answer.
_NEGLIGIBLE = 1e-6
# GeoTIFF tag and GeoKey numbers (GeoTIFF 1.1, OGC 19-008r4).
_TAG_PIXEL_SCALE, _TAG_TIEPOINT, _TAG_GEOKEYS, _TAG_NODATA = 33550, 33922, 34735, 42113
_KEY_MODEL_TYPE, _KEY_RASTER_TYPE, _KEY_GEOGRAPHIC, _KEY_PROJECTED = 1024, 1025, 2048, 3072
_KEY_LINEAR_UNITS, _METRE, _PIXEL_IS_POINT, _USER_DEFINED = 3076, 9001, 2, 32767


class TerrainError(GatewayError, ValueError):
    """Raised for a DEM tile that cannot be read or understood; the message names the file."""


@dataclass(frozen=True, slots=True)
class GridGeometry:
    """Where a grid's samples are: sample (row, col) is at (x0 + col·dx, y0 − row·dy).

    ``x``/``y`` are the CRS's easting/northing in metres, or lon/lat in degrees when the CRS
    is geographic. ``half_cell`` marks pixel-is-area rasters, whose footprint extends half a
    pixel beyond the outer samples; a point there takes the nearest edge sample's value.
    """

    crs: Geographic | TransverseMercator
    x0: float
    y0: float
    dx: float
    dy: float
    rows: int
    cols: int
    half_cell: bool = False

    def bounds(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the area this grid answers for, in CRS units."""
        pad_x, pad_y = (self.dx / 2, self.dy / 2) if self.half_cell else (0.0, 0.0)
        east = self.x0 + (self.cols - 1) * self.dx
        south = self.y0 - (self.rows - 1) * self.dy
        return self.x0 - pad_x, south - pad_y, east + pad_x, self.y0 + pad_y

    def covers(self, x: float, y: float) -> bool:
        """True if (x, y), in this grid's CRS, is inside the grid's area."""
        west, south, east, north = self.bounds()
        return west <= x <= east and south <= y <= north

    def sample_position(self, x: float, y: float) -> tuple[float, float]:
        """Fractional (row, col) of (x, y), clamped to the grid of samples."""
        row = min(max((self.y0 - y) / self.dy, 0.0), self.rows - 1.0)
        col = min(max((x - self.x0) / self.dx, 0.0), self.cols - 1.0)
        return row, col


class DemTile:
    """A loaded tile: its geometry and bilinear elevation lookups."""

    def __init__(self, path: Path, geometry: GridGeometry, nbytes: int) -> None:
        self.path = path
        self.geometry = geometry
        self.nbytes = nbytes

    def _sample(self, row: int, col: int) -> float | None:
        """The sample at (row, col) in metres, or None where the grid has no data."""
        raise NotImplementedError

    def elevation(self, lat: float, lon: float) -> float | None:
        """Bilinear elevation (m) at a WGS 84 point, or None outside the tile or over a void."""
        x, y = self.geometry.crs.forward(lat, lon)
        return self.elevation_xy(x, y) if self.geometry.covers(x, y) else None

    def elevation_xy(self, x: float, y: float) -> float | None:
        """Bilinear elevation (m) at (x, y) in the tile's CRS; None if a needed sample is void."""
        g = self.geometry
        row_f, col_f = g.sample_position(x, y)
        row, col = min(int(row_f), g.rows - 2), min(int(col_f), g.cols - 2)
        fy, fx = row_f - row, col_f - col
        total = used = 0.0
        for r, c, weight in (
            (row, col, (1 - fy) * (1 - fx)),
            (row, col + 1, (1 - fy) * fx),
            (row + 1, col, fy * (1 - fx)),
            (row + 1, col + 1, fy * fx),
        ):
            if weight < _NEGLIGIBLE:
                continue  # a void that does not contribute must not hide a good value
            value = self._sample(r, c)
            if value is None:
                return None
            total += weight * value
            used += weight
        return total / used

    def close(self) -> None:
        """Release the tile's memory or mapping; further lookups are an error."""


def hgt_geometry(path: Path) -> GridGeometry:
    """The geometry of an SRTM tile from its name and size; ``TerrainError`` if neither fits."""
    match = _HGT_NAME.match(path.name)
    if match is None:
        raise TerrainError(f"{path}: expected a name like N65E021.hgt")
    ns, lat, ew, lon = match.groups()
    south = int(lat) * (1 if ns.upper() == "N" else -1)
    west = int(lon) * (1 if ew.upper() == "E" else -1)
    size = path.stat().st_size
    samples = math.isqrt(size // 2)
    if samples * samples * 2 != size or samples not in (1201, 3601):
        raise TerrainError(f"{path}: {size} bytes is not a 1201² or 3601² int16 grid")
    step = 1.0 / (samples - 1)
    return GridGeometry(GEOGRAPHIC, west, south + 1.0, step, step, samples, samples)


class HgtTile(DemTile):
    """One SRTM ``.hgt`` tile, memory-mapped so a lookup reads only the pages it touches."""

    def __init__(self, path: Path) -> None:
        geometry = hgt_geometry(path)
        with path.open("rb") as handle:
            self._map = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
        super().__init__(path, geometry, len(self._map))

    def _sample(self, row: int, col: int) -> float | None:
        (value,) = struct.unpack_from(">h", self._map, 2 * (row * self.geometry.cols + col))
        return None if value == _HGT_VOID else float(value)

    def close(self) -> None:
        """Unmap the file."""
        self._map.close()


@dataclass(frozen=True, slots=True)
class GeoTiffHeader:
    """What a GeoTIFF's header says: where its samples are, and its no-data value."""

    geometry: GridGeometry
    nodata: float | None


def read_geotiff_header(path: Path) -> GeoTiffHeader:
    """Read a GeoTIFF's header only (not its raster).

    Raises ``TerrainError`` naming the file for anything this reader cannot use: no
    tie point or scale, more than one band, an unsupported CRS, or a compression that
    needs ``imagecodecs`` when it is not installed.
    """
    tifffile = _tifffile(path)
    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            tags = {tag.code: tag.value for tag in page.tags.values()}
            shape, samples = page.shape, page.samplesperpixel
            compression, predictor = page.compression, page.predictor
    except (OSError, ValueError, IndexError, KeyError) as exc:
        raise TerrainError(f"{path}: not a readable TIFF ({exc})") from exc
    if samples != 1 or len(shape) != 2:
        raise TerrainError(f"{path}: expected one band, found shape {shape}")
    if compression not in tifffile.TIFF.DECOMPRESSORS or predictor not in (
        tifffile.TIFF.UNPREDICTORS
    ):
        raise TerrainError(
            f"{path}: compression {compression!r} with predictor {predictor!r} needs "
            "the imagecodecs package (pip install 'fischer-gateway[terrain]')"
        )
    if _TAG_PIXEL_SCALE not in tags or _TAG_TIEPOINT not in tags:
        raise TerrainError(
            f"{path}: needs GeoTIFF ModelPixelScale and ModelTiepoint tags "
            "(rotated ModelTransformation grids are not supported)"
        )
    keys = _geokeys(tags.get(_TAG_GEOKEYS))
    try:
        crs = crs_from_epsg(_epsg(path, keys))
    except ProjectionError as exc:
        raise TerrainError(f"{path}: {exc}") from exc
    scale, tie = tags[_TAG_PIXEL_SCALE], tags[_TAG_TIEPOINT]
    dx, dy = float(scale[0]), float(scale[1])
    if dx <= 0 or dy <= 0:
        raise TerrainError(f"{path}: pixel scale must be positive, found {dx}, {dy}")
    # The tie point maps raster (I, J) to model (X, Y). Pixel-is-area rasters have raster
    # coordinate c at the pixel's corner, so the sample sits at c + 0.5.
    half_cell = keys.get(_KEY_RASTER_TYPE) != _PIXEL_IS_POINT
    offset = 0.5 if half_cell else 0.0
    x0 = float(tie[3]) + (offset - float(tie[0])) * dx
    y0 = float(tie[4]) - (offset - float(tie[1])) * dy
    rows, cols = int(shape[0]), int(shape[1])
    if rows < 2 or cols < 2:
        raise TerrainError(f"{path}: a {rows}×{cols} grid is too small to interpolate")
    nodata = _nodata(path, tags.get(_TAG_NODATA))
    return GeoTiffHeader(GridGeometry(crs, x0, y0, dx, dy, rows, cols, half_cell), nodata)


def _tifffile(path: Path) -> Any:
    try:
        import tifffile
    except ImportError as exc:
        raise TerrainError(
            f"{path}: GeoTIFF sources need tifffile (pip install 'fischer-gateway[terrain]')"
        ) from exc
    return tifffile


def _geokeys(directory: Any) -> dict[int, int]:
    """GeoKeys stored inline in the GeoKeyDirectory (the ones holding codes, not strings)."""
    if directory is None:
        return {}
    values = [int(v) for v in directory]
    count = values[3] if len(values) >= 4 else 0
    keys: dict[int, int] = {}
    for i in range(count):
        key, location, _, value = values[4 + 4 * i : 8 + 4 * i]
        if location == 0:
            keys[key] = value
    return keys


def _epsg(path: Path, keys: dict[int, int]) -> int:
    if not keys:
        raise TerrainError(f"{path}: no GeoKeyDirectory, so its coordinate system is unknown")
    model = keys.get(_KEY_MODEL_TYPE)
    code = keys.get(_KEY_PROJECTED) if model == 1 else keys.get(_KEY_GEOGRAPHIC)
    if code is None or code == _USER_DEFINED:
        raise TerrainError(f"{path}: the coordinate system has no EPSG code (user-defined)")
    if model == 1 and keys.get(_KEY_LINEAR_UNITS, _METRE) != _METRE:
        raise TerrainError(f"{path}: projected units must be metres")
    return code


def _nodata(path: Path, text: Any) -> float | None:
    if text is None:
        return None
    try:
        return float(str(text).strip().rstrip("\x00"))
    except ValueError as exc:
        raise TerrainError(f"{path}: GDAL_NODATA {text!r} is not a number") from exc


class GeoTiffTile(DemTile):
    """A single-band GeoTIFF tile, decoded into memory when first needed."""

    def __init__(self, path: Path) -> None:
        header = read_geotiff_header(path)
        tifffile = _tifffile(path)
        try:
            data = tifffile.imread(path, key=0)
        except (OSError, ValueError, KeyError) as exc:
            raise TerrainError(f"{path}: cannot decode the raster ({exc})") from exc
        self._data: Any = data
        self._nodata = header.nodata
        super().__init__(path, header.geometry, int(data.nbytes))

    def _sample(self, row: int, col: int) -> float | None:
        value = float(self._data[row, col])
        if math.isnan(value) or value == self._nodata:
            return None
        return value

    def close(self) -> None:
        """Drop the decoded raster."""
        self._data = None
