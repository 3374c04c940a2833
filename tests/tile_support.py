"""Small raster tiles made in the test: one-colour PNGs, as a z/x/y directory or an MBTiles file.

No image library: a PNG is its signature, an IHDR, one IDAT (zlib) and an IEND chunk. The
MBTiles file is real SQLite (the MBTiles 1.3 layout: ``metadata`` and ``tiles``, rows in TMS
order, ``y`` counted from the south).
"""

from __future__ import annotations

import sqlite3
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

Colour = tuple[int, int, int]


def png(colour: Colour, size: int = 256) -> bytes:
    """A ``size`` x ``size`` PNG of one colour (8-bit RGB)."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body) & 0xFFFFFFFF
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    row = b"\x00" + bytes(colour) * size  # filter type 0, then the pixels
    header = struct.pack(">IIBBBBB", size, size, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(row * size, 9))
        + chunk(b"IEND", b"")
    )


def write_mbtiles(
    path: Path, zooms: range, colour: Callable[[int, int, int], Colour], **metadata: str
) -> Path:
    """An MBTiles file with every tile of ``zooms``; ``colour(z, x, y)`` with XYZ ``y``."""
    conn = sqlite3.connect(path)
    try:
        conn.execute("CREATE TABLE metadata (name TEXT, value TEXT)")
        conn.execute(
            "CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, "
            "tile_data BLOB)"
        )
        conn.executemany(
            "INSERT INTO metadata VALUES (?, ?)",
            {"name": "test", "format": "png", **metadata}.items(),
        )
        made: dict[Colour, bytes] = {}
        for z in zooms:
            for x in range(2**z):
                for y in range(2**z):
                    rgb = colour(z, x, y)
                    data = made.setdefault(rgb, png(rgb))
                    conn.execute(
                        "INSERT INTO tiles VALUES (?, ?, ?, ?)", (z, x, 2**z - 1 - y, data)
                    )
        conn.commit()
    finally:
        conn.close()
    return path


def write_directory(root: Path, tiles: dict[tuple[int, int, int], Colour]) -> Path:
    """A z/x/y.png directory holding ``tiles``."""
    for (z, x, y), rgb in tiles.items():
        target = root / str(z) / str(x) / f"{y}.png"
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(png(rgb))
    return root
