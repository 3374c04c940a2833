"""Ground elevation from DEM tiles the operator supplies; AGL, its uncertainty, safety floors.

Sources are tried in the configured order (e.g. Lantmäteriet's 2 m grid, then SRTM 30 m); the
first that covers a point with data answers. Nothing is downloaded. SRTM ``.hgt`` tiles
(big-endian int16, 1201 or 3601 samples square, −32768 = void, named like ``N65E021.hgt`` for
the 1°×1° cell whose south-west corner is 65 N 21 E) are memory-mapped, so a lookup touches only
the pages it reads. GeoTIFF tiles (single band, north-up, with GeoTIFF model tie-point and pixel
scale tags, in geographic coordinates) are read with ``tifffile`` (optional dependency).
Elevations are bilinearly interpolated.

AGL uncertainty = √(σ_baro² + σ_dem²); a commanded altitude is kept at least 3σ above ground.
"""

from __future__ import annotations

import math
import mmap
import re
import struct
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

from gateway.errors import GatewayError

__all__ = [
    "DemSource",
    "GeoTiffTile",
    "HgtTile",
    "TerrainError",
    "TerrainModel",
    "agl_from_msl",
    "agl_sigma",
    "safe_floor_agl_m",
]

_VOID = -32768
_HGT_NAME = re.compile(r"^([NS])(\d{2})([EW])(\d{3})\.hgt$", re.IGNORECASE)


class TerrainError(GatewayError, ValueError):
    """Raised for a DEM tile that cannot be read or understood."""


def agl_sigma(sigma_baro_m: float, sigma_dem_m: float) -> float:
    """1σ uncertainty of height above ground from barometric and DEM errors (m)."""
    return math.hypot(sigma_baro_m, sigma_dem_m)


def agl_from_msl(alt_msl_m: float, ground_msl_m: float) -> float:
    """Height above ground from altitude and ground elevation, both above mean sea level."""
    return alt_msl_m - ground_msl_m


def safe_floor_agl_m(sigma_m: float, clearance_m: float = 0.0) -> float:
    """The lowest AGL to command: the wanted clearance plus 3σ of AGL uncertainty."""
    return clearance_m + 3.0 * sigma_m


class Tile(Protocol):
    """A DEM tile: its extent and an elevation lookup."""

    def covers(self, lat: float, lon: float) -> bool:
        """True if the point is inside this tile."""
        ...

    def elevation(self, lat: float, lon: float) -> float | None:
        """Bilinear elevation (m), or None where the tile has no data."""
        ...


def _bilinear(grid: Sequence[float | None], row: float, col: float) -> float | None:
    """Interpolate a 2×2 neighbourhood ``grid`` (nw, ne, sw, se) at fractional offsets."""
    nw, ne, sw, se = grid
    if nw is None or ne is None or sw is None or se is None:
        return None
    top = nw + (ne - nw) * col
    bottom = sw + (se - sw) * col
    return top + (bottom - top) * row


class HgtTile:
    """One SRTM ``.hgt`` tile, memory-mapped."""

    def __init__(self, path: Path) -> None:
        match = _HGT_NAME.match(path.name)
        if match is None:
            raise TerrainError(f"{path}: expected a name like N65E021.hgt")
        ns, lat, ew, lon = match.groups()
        self.south = int(lat) * (1 if ns.upper() == "N" else -1)
        self.west = int(lon) * (1 if ew.upper() == "E" else -1)
        size = path.stat().st_size
        samples = math.isqrt(size // 2)
        if samples * samples * 2 != size or samples not in (1201, 3601):
            raise TerrainError(f"{path}: {size} bytes is not a 1201² or 3601² int16 grid")
        self.samples = samples
        with path.open("rb") as handle:
            self._map = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)

    def covers(self, lat: float, lon: float) -> bool:
        """True if the point is inside the tile's 1°×1° cell."""
        return self.south <= lat <= self.south + 1 and self.west <= lon <= self.west + 1

    def _at(self, row: int, col: int) -> float | None:
        (value,) = struct.unpack_from(">h", self._map, 2 * (row * self.samples + col))
        return None if value == _VOID else float(value)

    def elevation(self, lat: float, lon: float) -> float | None:
        """Bilinear elevation (m MSL, EGM96) at the point, None over a void."""
        span = self.samples - 1
        y = (self.south + 1 - lat) * span  # row 0 is the north edge
        x = (lon - self.west) * span
        row, col = min(int(y), span - 1), min(int(x), span - 1)
        grid = [self._at(row, col), self._at(row, col + 1)]
        grid += [self._at(row + 1, col), self._at(row + 1, col + 1)]
        return _bilinear(grid, y - row, x - col)


class GeoTiffTile:
    """A single-band, north-up GeoTIFF in geographic coordinates (read whole, once)."""

    def __init__(self, path: Path) -> None:
        try:
            import tifffile
        except ImportError as exc:
            raise TerrainError(f"{path}: GeoTIFF sources need 'pip install tifffile'") from exc
        try:
            with tifffile.TiffFile(path) as tif:
                page = tif.pages[0]
                tags = page.tags  # type: ignore[union-attr]
                scale = tags["ModelPixelScaleTag"].value
                tie = tags["ModelTiepointTag"].value
                nodata_tag = tags.get("GDAL_NODATA")
                data = page.asarray()
        except (OSError, KeyError, ValueError) as exc:
            raise TerrainError(f"{path}: not a readable GeoTIFF with tie point and scale") from exc
        if data.ndim != 2:
            raise TerrainError(f"{path}: expected one band, found shape {data.shape}")
        self.rows, self.cols = data.shape
        self._data = data
        self.dx, self.dy = float(scale[0]), float(scale[1])
        # Tie point: raster (i, j) maps to model (x, y); pixel centres (PixelIsPoint) assumed.
        self.west = float(tie[3]) - float(tie[0]) * self.dx
        self.north = float(tie[4]) + float(tie[1]) * self.dy
        self.nodata = float(nodata_tag.value) if nodata_tag is not None else None

    def covers(self, lat: float, lon: float) -> bool:
        """True if the point is inside the grid of sample centres."""
        east = self.west + (self.cols - 1) * self.dx
        south = self.north - (self.rows - 1) * self.dy
        return bool(south <= lat <= self.north and self.west <= lon <= east)

    def _at(self, row: int, col: int) -> float | None:
        value = float(self._data[row, col])
        return None if math.isnan(value) or value == self.nodata else value

    def elevation(self, lat: float, lon: float) -> float | None:
        """Bilinear elevation (m) at the point, None over no-data."""
        y = (self.north - lat) / self.dy
        x = (lon - self.west) / self.dx
        row, col = min(int(y), self.rows - 2), min(int(x), self.cols - 2)
        grid = [self._at(row, col), self._at(row, col + 1)]
        grid += [self._at(row + 1, col), self._at(row + 1, col + 1)]
        return _bilinear(grid, y - row, x - col)


@dataclass(frozen=True)
class DemSource:
    """A directory of tiles of one kind, with the DEM's own 1σ vertical error."""

    name: str
    directory: Path
    kind: Literal["hgt", "geotiff"]
    sigma_m: float


class TerrainModel:
    """Looks points up in the configured sources, in order, with an LRU cache of tiles."""

    def __init__(self, sources: Sequence[DemSource], *, cache_tiles: int = 16) -> None:
        self.sources = list(sources)
        self._cache: OrderedDict[Path, Tile] = OrderedDict()
        self._cache_tiles = cache_tiles
        self._index: list[tuple[DemSource, list[Path]]] = [
            (s, sorted(s.directory.glob("*.hgt" if s.kind == "hgt" else "*.tif*")))
            for s in self.sources
        ]

    def _tile(self, source: DemSource, path: Path) -> Tile:
        tile = self._cache.get(path)
        if tile is None:
            tile = HgtTile(path) if source.kind == "hgt" else GeoTiffTile(path)
            self._cache[path] = tile
            if len(self._cache) > self._cache_tiles:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(path)
        return tile

    def lookup(self, lat: float, lon: float) -> tuple[float, DemSource] | None:
        """(ground elevation m, the source that answered), or None if no source covers it."""
        for source, paths in self._index:
            for path in paths:
                if source.kind == "hgt" and not _hgt_may_cover(path, lat, lon):
                    continue
                tile = self._tile(source, path)
                if tile.covers(lat, lon):
                    value = tile.elevation(lat, lon)
                    if value is not None:
                        return value, source
        return None

    def ground_elevation_m(self, lat: float, lon: float) -> float | None:
        """Ground elevation (m) at the point, or None where no tile has data."""
        found = self.lookup(lat, lon)
        return None if found is None else found[0]


def _hgt_may_cover(path: Path, lat: float, lon: float) -> bool:
    match = _HGT_NAME.match(path.name)
    if match is None:
        return False
    ns, south, ew, west = match.groups()
    s = int(south) * (1 if ns.upper() == "N" else -1)
    w = int(west) * (1 if ew.upper() == "E" else -1)
    return s <= lat <= s + 1 and w <= lon <= w + 1
