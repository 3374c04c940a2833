"""Ground elevation from the operator's DEM tiles; height above ground and its uncertainty.

``TerrainModel`` answers "how high is the ground here?" from DEM sources tried in the
configured order (e.g. ``lantmateriet_2m`` GeoTIFFs, then ``srtm_30m`` ``.hgt`` tiles): the
first source with data at a point answers, so a void or a gap in the fine grid falls through
to the coarse one. Nothing is downloaded. Tile headers are indexed once, at construction, so
a lookup touches only the tiles that can cover the point; decoded tiles stay in an LRU cache
bounded by count and by bytes.

AGL = MSL altitude − ground elevation. Its 1σ uncertainty is √(σ_baro² + σ_dem²), and a
commanded altitude keeps a 3σ margin above the wanted clearance.

Vertical datums differ slightly (SRTM: EGM96; Lantmäteriet: RH 2000; the autopilot: its GNSS
receiver's geoid, usually EGM96); in Sweden they agree to well under a metre, inside σ_dem.
"""

from __future__ import annotations

import math
from collections import OrderedDict, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import structlog

from gateway.domain.dem import (
    DemTile,
    GeoTiffTile,
    GridGeometry,
    HgtTile,
    TerrainError,
    hgt_geometry,
    read_geotiff_header,
)
from gateway.domain.projection import Geographic, TransverseMercator

__all__ = [
    "AglEstimate",
    "DemSource",
    "TerrainError",
    "TerrainModel",
    "agl_from_msl",
    "agl_sigma",
    "msl_from_agl",
    "safe_floor_agl_m",
    "safe_floor_msl_m",
]

log = structlog.get_logger(__name__)

#: The multiple of σ_AGL kept between a commanded altitude and the wanted clearance.
SAFETY_SIGMAS = 3.0


def agl_sigma(sigma_baro_m: float, sigma_dem_m: float) -> float:
    """1σ uncertainty (m) of height above ground from independent altimeter and DEM errors."""
    return math.hypot(sigma_baro_m, sigma_dem_m)


def agl_from_msl(alt_msl_m: float, ground_msl_m: float) -> float:
    """Height above ground (m) from an altitude and the ground elevation, both MSL metres."""
    return alt_msl_m - ground_msl_m


def msl_from_agl(alt_agl_m: float, ground_msl_m: float) -> float:
    """Altitude above mean sea level (m) of a height above ground at a ground elevation."""
    return alt_agl_m + ground_msl_m


def safe_floor_agl_m(sigma_m: float, clearance_m: float = 0.0) -> float:
    """The lowest AGL (m) to command: the wanted clearance plus 3σ of AGL uncertainty."""
    if sigma_m < 0 or clearance_m < 0:
        raise ValueError(f"σ and clearance must not be negative, found {sigma_m}, {clearance_m}")
    return clearance_m + SAFETY_SIGMAS * sigma_m


def safe_floor_msl_m(ground_msl_m: float, sigma_m: float, clearance_m: float = 0.0) -> float:
    """The lowest MSL altitude (m) to command over ground at ``ground_msl_m``."""
    return msl_from_agl(safe_floor_agl_m(sigma_m, clearance_m), ground_msl_m)


@dataclass(frozen=True)
class DemSource:
    """A directory of DEM tiles of one kind, with the DEM's own 1σ vertical error (m)."""

    name: str
    directory: Path
    kind: Literal["hgt", "geotiff"]
    sigma_m: float


@dataclass(frozen=True, slots=True)
class AglEstimate:
    """Height above ground at a point, its 1σ (m), and the ground and source it came from."""

    alt_agl_m: float
    sigma_m: float
    ground_msl_m: float
    source: str


@dataclass(frozen=True, slots=True)
class _Entry:
    path: Path
    kind: Literal["hgt", "geotiff"]
    geometry: GridGeometry


_Bucket = tuple[int, int]


class _SourceIndex:
    """The tiles of one source, bucketed on a grid per CRS so a lookup checks only a few."""

    def __init__(self, source: DemSource, entries: list[_Entry]) -> None:
        self.source = source
        self._groups: list[
            tuple[Geographic | TransverseMercator, float, dict[_Bucket, list[_Entry]]]
        ] = []
        by_crs: dict[int, list[_Entry]] = defaultdict(list)
        for entry in entries:
            by_crs[entry.geometry.crs.epsg].append(entry)
        for group in by_crs.values():
            # Buckets as large as the largest tile put each tile in at most four of them.
            extents = [e.geometry.bounds() for e in group]
            size = max(max(e - w, n - s) for w, s, e, n in extents)
            buckets: dict[_Bucket, list[_Entry]] = defaultdict(list)
            for entry, (west, south, east, north) in zip(group, extents, strict=True):
                for bx in range(math.floor(west / size), math.floor(east / size) + 1):
                    for by in range(math.floor(south / size), math.floor(north / size) + 1):
                        buckets[(bx, by)].append(entry)
            self._groups.append((group[0].geometry.crs, size, dict(buckets)))

    def candidates(self, lat: float, lon: float) -> list[tuple[_Entry, float, float]]:
        """Tiles covering the point, each with the point in that tile's CRS."""
        found = []
        for crs, size, buckets in self._groups:
            x, y = crs.forward(lat, lon)
            if not (math.isfinite(x) and math.isfinite(y)):
                continue  # too far from this projection's meridian for any of its tiles
            for entry in buckets.get((math.floor(x / size), math.floor(y / size)), ()):
                if entry.geometry.covers(x, y):
                    found.append((entry, x, y))
        return found


class TerrainModel:
    """Ground elevation from DEM sources tried in order, with an LRU cache of decoded tiles.

    Construction reads every tile's header and raises ``TerrainError`` listing each file it
    cannot use. Lookups are synchronous and cheap once a tile is cached; loading a tile
    memory-maps (``.hgt``) or decodes (GeoTIFF, a few tens of ms for a 2.5 km Lantmäteriet
    tile) it. A tile that fails to decode later is logged once and skipped.
    """

    def __init__(
        self,
        sources: Sequence[DemSource],
        *,
        cache_tiles: int = 16,
        cache_bytes: int = 512 * 2**20,
    ) -> None:
        self.sources = list(sources)
        self._cache: OrderedDict[Path, DemTile] = OrderedDict()
        self._cache_tiles = max(cache_tiles, 1)
        self._cache_bytes = cache_bytes
        self._bad: set[Path] = set()
        problems: list[str] = []
        self._indexes = [_SourceIndex(s, _scan(s, problems)) for s in self.sources]
        if problems:
            more = f"\n… and {len(problems) - 20} more" if len(problems) > 20 else ""
            raise TerrainError("unusable DEM tiles:\n" + "\n".join(problems[:20]) + more)

    def lookup(self, lat: float, lon: float) -> tuple[float, DemSource] | None:
        """(ground elevation in m MSL, the source that answered), or None if none has data."""
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            return None  # also rejects NaN, which fails every comparison
        for index in self._indexes:
            for entry, x, y in index.candidates(lat, lon):
                tile = self._tile(entry)
                value = None if tile is None else tile.elevation_xy(x, y)
                if value is not None:
                    return value, index.source
        return None

    def ground_elevation_m(self, lat: float, lon: float) -> float | None:
        """Ground elevation (m MSL) at a WGS 84 point, or None where no tile has data."""
        found = self.lookup(lat, lon)
        return None if found is None else found[0]

    def agl(
        self, lat: float, lon: float, alt_msl_m: float, baro_sigma_m: float
    ) -> AglEstimate | None:
        """Height above ground and its 1σ at a point, or None where no DEM covers it."""
        found = self.lookup(lat, lon)
        if found is None:
            return None
        ground, source = found
        return AglEstimate(
            agl_from_msl(alt_msl_m, ground),
            agl_sigma(baro_sigma_m, source.sigma_m),
            ground,
            source.name,
        )

    @property
    def cached_paths(self) -> tuple[Path, ...]:
        """The tiles held in the cache, least recently used first."""
        return tuple(self._cache)

    def close(self) -> None:
        """Release every cached tile."""
        while self._cache:
            self._cache.popitem(last=False)[1].close()

    def _tile(self, entry: _Entry) -> DemTile | None:
        tile = self._cache.get(entry.path)
        if tile is not None:
            self._cache.move_to_end(entry.path)
            return tile
        if entry.path in self._bad:
            return None
        try:
            tile = HgtTile(entry.path) if entry.kind == "hgt" else GeoTiffTile(entry.path)
        except (OSError, TerrainError) as exc:
            # A tile that indexed but will not decode (truncated since, or corrupt data)
            # must not stop telemetry: the next source answers instead.
            self._bad.add(entry.path)
            log.warning("dem_tile_skipped", path=str(entry.path), error=str(exc))
            return None
        self._cache[entry.path] = tile
        total = sum(t.nbytes for t in self._cache.values())
        while len(self._cache) > 1 and (
            len(self._cache) > self._cache_tiles or total > self._cache_bytes
        ):
            _, evicted = self._cache.popitem(last=False)
            total -= evicted.nbytes
            evicted.close()
        return tile


def _scan(source: DemSource, problems: list[str]) -> list[_Entry]:
    """Index one source's directory; unusable files are added to ``problems``."""
    if not source.directory.is_dir():
        problems.append(f"{source.directory}: source {source.name!r} is not a directory")
        return []
    suffixes = (".hgt",) if source.kind == "hgt" else (".tif", ".tiff")
    entries = []
    for path in sorted(source.directory.iterdir()):
        if path.suffix.lower() not in suffixes or not path.is_file():
            continue
        try:
            geometry = (
                hgt_geometry(path) if source.kind == "hgt" else read_geotiff_header(path).geometry
            )
        except (OSError, TerrainError) as exc:
            problems.append(str(exc))
            continue
        entries.append(_Entry(path, source.kind, geometry))
    return entries
