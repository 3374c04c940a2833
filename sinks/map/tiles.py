"""Local raster tiles for the base map: a directory of ``z/x/y`` files or an MBTiles file.

Offline maps (Lantmäteriet's, or any XYZ raster set) are served by the map's own listener
at ``/tiles/{z}/{x}/{y}`` (docs/map.md §7). The address carries only three integers, checked
against the zoom's range before they are used; a file path is built from them alone, so no
request can name a file outside the set. An MBTiles file (SQLite, the MBTiles 1.3 layout) is
opened read-only and queried with parameters; its rows are TMS (``y`` counted from the south),
which ``tile`` turns round. Vector tiles (``pbf``) are refused when the sink opens.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

__all__ = ["MAX_TILE_BYTES", "MEDIA_TYPES", "TileSet", "TilesError", "open_tiles", "sniff"]

#: A stored tile larger than this is not served (a raster tile is some tens of kilobytes).
MAX_TILE_BYTES = 4 * 1024 * 1024
MAX_ZOOM = 24
MEDIA_TYPES = {"png": "image/png", "jpg": "image/jpeg", "jpeg": "image/jpeg", "webp": "image/webp"}


class TilesError(ValueError):
    """The tile set cannot be used (named in the message)."""


def sniff(data: bytes) -> str | None:
    """The media type of an image by its first bytes; None for anything else."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "image/png"
    if data.startswith(b"\xff\xd8\xff"):
        return "image/jpeg"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "image/webp"
    return None


@dataclass(frozen=True, slots=True)
class TileSet:
    """One tile set; ``tile`` answers one request (blocking: call it in a worker thread)."""

    path: Path
    min_zoom: int
    max_zoom: int
    attribution: str
    kind: str  # "directory" or "mbtiles"
    extension: str = "png"

    def valid(self, z: int, x: int, y: int) -> bool:
        """True when ``z``/``x``/``y`` name a tile this set can have."""
        return self.min_zoom <= z <= self.max_zoom and 0 <= x < 2**z and 0 <= y < 2**z

    def tile(self, z: int, x: int, y: int) -> tuple[bytes, str] | None:
        """The tile's bytes and media type; None when the set has none there."""
        if not self.valid(z, x, y):
            return None
        if self.kind == "mbtiles":
            return _mbtiles_tile(self.path, z, x, (2**z - 1) - y)
        file = self.path / str(z) / str(x) / f"{y}.{self.extension}"
        try:
            with file.open("rb") as handle:
                data = handle.read(MAX_TILE_BYTES + 1)
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            return None
        except OSError:
            return None
        if len(data) > MAX_TILE_BYTES:
            return None
        media = sniff(data)
        return None if media is None else (data, media)

    def describe(self) -> dict[str, object]:
        """What the page needs to draw the set."""
        return {
            "min_zoom": self.min_zoom,
            "max_zoom": self.max_zoom,
            "attribution": self.attribution,
            "kind": self.kind,
        }


def _connect(path: Path) -> sqlite3.Connection:
    """A read-only connection to ``path`` (opening one is cheap next to a tile's transfer)."""
    uri = "file:" + quote(str(path.absolute())) + "?mode=ro"
    conn = sqlite3.connect(uri, uri=True)
    conn.execute("PRAGMA query_only = ON")
    return conn


def _mbtiles_tile(path: Path, z: int, x: int, row: int) -> tuple[bytes, str] | None:
    try:
        conn = _connect(path)
        try:
            found = conn.execute(
                "SELECT length(tile_data), tile_data FROM tiles "
                "WHERE zoom_level = ? AND tile_column = ? AND tile_row = ? LIMIT 1",
                (z, x, row),
            ).fetchone()
        finally:
            conn.close()
    except sqlite3.Error:
        return None
    if found is None or not isinstance(found[1], bytes) or found[0] > MAX_TILE_BYTES:
        return None
    media = sniff(found[1])
    return None if media is None else (found[1], media)


def open_tiles(
    path: Path, *, fmt: str, min_zoom: int | None, max_zoom: int | None, attribution: str
) -> TileSet:
    """Check the tile set at ``path`` and describe it; ``TilesError`` naming what is wrong."""
    if path.is_dir():
        if fmt not in MEDIA_TYPES:
            raise TilesError(f"tiles {path}: format {fmt!r} is not one of png, jpg, webp")
        zooms = sorted(int(p.name) for p in path.iterdir() if p.name.isdigit() and p.is_dir())
        zooms = [z for z in zooms if z <= MAX_ZOOM]
        if not zooms:
            raise TilesError(f"tiles {path}: no zoom directories (z/x/y.{fmt}) in it")
        low = zooms[0] if min_zoom is None else min_zoom
        high = zooms[-1] if max_zoom is None else max_zoom
        return TileSet(path, low, high, attribution, "directory", fmt)
    if not path.is_file():
        raise TilesError(f"tiles {path}: neither a directory of z/x/y tiles nor a file")
    try:
        conn = _connect(path)
        try:
            meta = dict(conn.execute("SELECT name, value FROM metadata").fetchall())
            low_high = conn.execute("SELECT min(zoom_level), max(zoom_level) FROM tiles").fetchone()
        finally:
            conn.close()
    except sqlite3.Error as exc:
        raise TilesError(f"tiles {path}: not an MBTiles file ({exc})") from None
    declared = str(meta.get("format", "png")).lower()
    if declared not in MEDIA_TYPES:
        raise TilesError(
            f"tiles {path}: format {declared!r}: only raster tiles (png, jpg, webp) are drawn"
        )
    if low_high is None or low_high[0] is None:
        raise TilesError(f"tiles {path}: the tiles table is empty")
    low = int(low_high[0]) if min_zoom is None else min_zoom
    high = min(int(low_high[1]), MAX_ZOOM) if max_zoom is None else max_zoom
    text = attribution or str(meta.get("attribution", ""))[:200]
    return TileSet(path, max(low, 0), high, text, "mbtiles", declared)
