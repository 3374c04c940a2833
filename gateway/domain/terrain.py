"""Ground elevation from the operator's DEM tiles; height above ground and its uncertainty.

``TerrainModel`` answers "how high is the ground here?" from DEM sources tried in the
configured order (e.g. ``lantmateriet_2m`` GeoTIFFs, then ``srtm_30m`` ``.hgt`` tiles): the
first source with data at a point answers, so a void or a gap in the fine grid falls through
to the coarse one. Nothing is downloaded. Tile headers are indexed once, at construction, so
a lookup touches only the tiles that can cover the point; decoded tiles stay in an LRU cache
bounded by count and by bytes.

AGL = MSL altitude − ground elevation. Its 1σ uncertainty is √(σ_baro² + σ_dem²), and a
commanded altitude keeps a 3σ margin above the wanted clearance.

An unusable DEM never stops telemetry. The gateway builds the model with ``strict=False``:
a source whose directory is missing, or a GeoTIFF source without ``tifffile`` installed, is
disabled; a tile that cannot be indexed or decoded (any error from the decoder) is skipped
for good; each is counted (``errors``), logged at most once a minute per source and reason,
and shown by ``status()``. Telemetry then flows without AGL where no source answers.
``check_sources`` finds the configuration problems without reading any tile, for
``check-config``. The default ``strict=True`` raises ``TerrainError`` instead.

Vertical datums differ slightly (SRTM: EGM96; Lantmäteriet: RH 2000; the autopilot: its GNSS
receiver's geoid, usually EGM96); in Sweden they agree to well under a metre, inside σ_dem.
"""

from __future__ import annotations

import math
from collections import Counter, OrderedDict, defaultdict
from collections.abc import Iterable, Sequence
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
from gateway.ops.logsetup import RateLimit

__all__ = [
    "AglEstimate",
    "DemSource",
    "TerrainError",
    "TerrainModel",
    "agl_from_msl",
    "agl_sigma",
    "check_sources",
    "msl_from_agl",
    "safe_floor_agl_m",
    "safe_floor_msl_m",
]

log = structlog.get_logger(__name__)

#: The multiple of σ_AGL kept between a commanded altitude and the wanted clearance.
SAFETY_SIGMAS = 3.0
#: At most one log record per source and failure reason in this many seconds.
DEM_LOG_INTERVAL_S = 60.0
_TIFFFILE_MISSING = "GeoTIFF sources need tifffile: pip install 'fischer-gateway[terrain]'"


def _has_tifffile() -> bool:
    try:
        import tifffile  # noqa: F401 - only whether it imports
    except ImportError:
        return False
    return True


def check_sources(sources: Iterable[DemSource]) -> list[tuple[int, str]]:
    """Configuration problems of DEM sources, as (index in ``sources``, message).

    Cheap (only tile headers are read), for ``check-config``: a directory that does not exist,
    a GeoTIFF source without ``tifffile`` installed, a directory with no tile of its kind,
    tiles whose headers cannot be read.
    The daemon runs without such a source (no AGL from it), so these are warnings.
    """
    problems: list[tuple[int, str]] = []
    for index, source in enumerate(sources):
        where = f"source {source.name!r}"
        if source.kind == "geotiff" and not _has_tifffile():
            problems.append((index, f"{where}: {_TIFFFILE_MISSING}"))
        if not source.directory.is_dir():
            problems.append((index, f"{where}: {source.directory} is not a directory"))
            continue
        try:
            names = [p.name for p in source.directory.iterdir()]
        except OSError as exc:
            problems.append((index, f"{where}: cannot list {source.directory}: {exc.strerror}"))
            continue
        suffixes = _SUFFIXES[source.kind]
        if not any(name.lower().endswith(suffixes) for name in names):
            wanted = " or ".join(suffixes)
            problems.append((index, f"{where}: no {wanted} tiles in {source.directory}"))
            continue
        # Reading each tile's header is cheap and finds tiles the daemon could never use.
        unreadable: list[str] = []
        if not _scan(source, unreadable) and unreadable:
            problems.append((index, f"{where}: every tile is unreadable: {unreadable[0]}"))
        elif unreadable:
            problems.append(
                (index, f"{where}: {len(unreadable)} unreadable tile(s): {unreadable[0]}")
            )
    return problems


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

    Construction reads every tile's header. With ``strict=True`` (the default) it raises
    ``TerrainError`` listing each file it cannot use; with ``strict=False`` it skips those
    tiles and disables a source that cannot work at all (see the module docstring). Lookups
    are synchronous, never raise, and are cheap once a tile is cached; loading a tile
    memory-maps (``.hgt``) or decodes (GeoTIFF, a few tens of ms for a 2.5 km Lantmäteriet
    tile) it. A tile that fails to decode later is logged and skipped.
    """

    def __init__(
        self,
        sources: Sequence[DemSource],
        *,
        cache_tiles: int = 16,
        cache_bytes: int = 512 * 2**20,
        strict: bool = True,
    ) -> None:
        self.sources = list(sources)
        self._cache: OrderedDict[Path, DemTile] = OrderedDict()
        self._cache_tiles = max(cache_tiles, 1)
        self._cache_bytes = cache_bytes
        self._bad: set[Path] = set()
        self._source_of: dict[Path, str] = {}
        self._disabled: dict[str, str] = {}
        self._tiles: Counter[str] = Counter()
        self._skipped: Counter[str] = Counter()
        self._log_limit = RateLimit(DEM_LOG_INTERVAL_S)
        self.errors: Counter[tuple[str, str]] = Counter()
        """Failures so far, by (source name, reason): what ``fg_dem_errors_total`` shows."""
        problems: list[str] = []
        self._indexes = []
        for source in self.sources:
            entries = self._index(source, problems, strict=strict)
            self._tiles[source.name] = len(entries)
            self._source_of.update((e.path, source.name) for e in entries)
            self._indexes.append(_SourceIndex(source, entries))
        if problems and strict:
            more = f"\n… and {len(problems) - 20} more" if len(problems) > 20 else ""
            raise TerrainError("unusable DEM tiles:\n" + "\n".join(problems[:20]) + more)

    def _index(self, source: DemSource, problems: list[str], *, strict: bool) -> list[_Entry]:
        if strict:
            return _scan(source, problems)
        if source.kind == "geotiff" and not _has_tifffile():
            self._failed(source.name, "no_tifffile", _TIFFFILE_MISSING)
            self._disable(source.name, "no_tifffile", _TIFFFILE_MISSING)
            return []
        found: list[str] = []
        entries = _scan(source, found)
        if not source.directory.is_dir():
            self._failed(source.name, "missing", found[0])
            self._disable(source.name, "missing", found[0])
            return []
        for problem in found:
            self._skipped[source.name] += 1
            self._failed(source.name, "unreadable", problem)
        if found and not entries:
            self._disable(source.name, "unreadable", f"every tile unreadable ({found[0]})")
        return entries

    def status(self) -> list[dict[str, object]]:
        """Per source: its state (``up`` or ``disabled``), why, and tiles usable and skipped."""
        return [
            {
                "source": source.name,
                "kind": source.kind,
                "directory": str(source.directory),
                "state": "disabled" if source.name in self._disabled else "up",
                "reason": self._disabled.get(source.name, ""),
                "tiles": self._tiles[source.name],
                "tiles_skipped": self._skipped[source.name],
            }
            for source in self.sources
        ]

    def is_source_up(self, name: str) -> bool:
        """False once the source ``name`` is disabled."""
        return name not in self._disabled

    def _failed(self, source: str, reason: str, detail: str) -> None:
        self.errors[(source, reason)] += 1
        if self._log_limit.allow((source, reason)):
            log.warning(
                "dem_error",
                source=source,
                reason=reason,
                detail=detail,
                count=self.errors[(source, reason)],
            )

    def _disable(self, source: str, reason: str, detail: str) -> None:
        if source not in self._disabled:
            self._disabled[source] = detail
            log.error("dem_source_disabled", source=source, reason=reason, detail=detail)

    def lookup(self, lat: float, lon: float) -> tuple[float, DemSource] | None:
        """(ground elevation in m MSL, the source that answered), or None if none has data."""
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            return None  # also rejects NaN, which fails every comparison
        for index in self._indexes:
            if index.source.name in self._disabled:
                continue
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
        except Exception as exc:  # noqa: BLE001 - decoders (imagecodecs, tifffile) raise many types
            # A tile that indexed but will not decode (truncated since, or corrupt data)
            # must not stop telemetry: the next source answers instead. Never retried.
            self._bad.add(entry.path)
            source = self._source_of.get(entry.path, "")
            self._tiles[source] -= 1
            self._skipped[source] += 1
            self.errors[(source, "undecodable")] += 1
            log.warning(
                "dem_tile_skipped",
                source=source,
                path=str(entry.path),
                error=f"{type(exc).__name__}: {exc}",
            )
            if self._tiles[source] <= 0:
                self._disable(source, "undecodable", "every tile of the source failed to decode")
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


_SUFFIXES: dict[str, tuple[str, ...]] = {"hgt": (".hgt",), "geotiff": (".tif", ".tiff")}


def _scan(source: DemSource, problems: list[str]) -> list[_Entry]:
    """Index one source's directory; unusable files are added to ``problems``."""
    try:
        paths = sorted(source.directory.iterdir())
    except OSError as exc:
        why = "is not a directory" if not source.directory.is_dir() else exc.strerror
        problems.append(f"{source.directory}: source {source.name!r} {why}")
        return []
    suffixes = _SUFFIXES[source.kind]
    entries = []
    for path in paths:
        if path.suffix.lower() not in suffixes or not path.is_file():
            continue
        try:
            geometry = (
                hgt_geometry(path) if source.kind == "hgt" else read_geotiff_header(path).geometry
            )
        except Exception as exc:  # noqa: BLE001 - a header parser of outside files; named below
            problems.append(str(exc) if isinstance(exc, TerrainError) else f"{path}: {exc!r}")
            continue
        entries.append(_Entry(path, source.kind, geometry))
    return entries
