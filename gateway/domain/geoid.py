"""EGM96 geoid undulation N, offline: height above the ellipsoid = MSL + N.

Two sources, both read once and never downloaded: the 30' grid shipped in
``gateway/data/egm96_30min.bin`` (derived from NGA's public-domain EGM96; provenance, format and
accuracy in ``gateway/data/README.md``), used by default, or a PROJ ``.gtx`` grid such as
Debian proj-data's 15' ``/usr/share/proj/egm96_15.gtx`` (four big-endian float64 south-west
latitude, west longitude, latitude step, longitude step; two int32 rows, columns; then rows of
big-endian float32 from the south). Interpolation is bilinear; longitudes wrap at ±180.
"""

from __future__ import annotations

import math
import struct
import zlib
from array import array
from functools import cache
from itertools import accumulate
from pathlib import Path

import gateway.events

__all__ = ["DATA_DIR", "GeoidGrid", "bundled_geoid"]

#: ``gateway/data``: the gateway's data files (a directory, not a package). Found from a module
#: file because under pytest ``gateway`` can resolve as a namespace with ``tests/gateway``.
DATA_DIR = Path(gateway.events.__file__).resolve().parent / "data"

_GTX_HEADER = struct.Struct(">ddddii")
_BUNDLED_MAGIC = b"FGGEOID1"
_BUNDLED_HEADER = struct.Struct("<ddddiid")
_BUNDLED_NAME = "egm96_30min.bin"


class GeoidGrid:
    """Geoid undulation N (metres) on a regular latitude/longitude grid."""

    def __init__(
        self,
        values: array[float] | array[int],
        *,
        lat0: float,
        lon0: float,
        dlat: float,
        dlon: float,
        rows: int,
        cols: int,
        scale: float = 1.0,
    ) -> None:
        if rows < 2 or cols < 2 or dlat <= 0 or dlon <= 0 or len(values) != rows * cols:
            raise ValueError(f"geoid grid of {rows}x{cols} does not match {len(values)} values")
        self._values = values
        self._scale = scale
        self.lat0, self.lon0, self.dlat, self.dlon = lat0, lon0, dlat, dlon
        self.rows, self.cols = rows, cols
        # Whether the columns go round the globe, so the last one meets the first.
        self._wraps = abs(cols * dlon - 360.0) < 1e-6

    @classmethod
    def from_gtx(cls, path: Path) -> GeoidGrid:
        """Read a PROJ ``.gtx`` grid; ``ValueError`` names the file if it is not one."""
        data = path.read_bytes()
        if len(data) < _GTX_HEADER.size:
            raise ValueError(f"{path}: too short for a GTX grid")
        lat0, lon0, dlat, dlon, rows, cols = _GTX_HEADER.unpack_from(data)
        values = array("f")
        values.frombytes(data[_GTX_HEADER.size : _GTX_HEADER.size + 4 * max(rows * cols, 0)])
        values.byteswap()  # big-endian on disk
        try:
            return cls(values, lat0=lat0, lon0=lon0, dlat=dlat, dlon=dlon, rows=rows, cols=cols)
        except ValueError as exc:
            raise ValueError(f"{path}: header and size of the GTX grid disagree") from exc

    @classmethod
    def from_bundled(cls, data: bytes) -> GeoidGrid:
        """Read the shipped grid format (``gateway/data/README.md``)."""
        if not data.startswith(_BUNDLED_MAGIC):
            raise ValueError("not a fischer-gateway geoid grid")
        start = len(_BUNDLED_MAGIC)
        lat0, lon0, dlat, dlon, rows, cols, scale = _BUNDLED_HEADER.unpack_from(data, start)
        deltas = array("h")
        deltas.frombytes(zlib.decompress(data[start + _BUNDLED_HEADER.size :]))
        if deltas.itemsize != 2 or len(deltas) != rows * cols:
            raise ValueError("geoid grid size disagrees with its header")
        values = array("i", accumulate(deltas))
        return cls(
            values, lat0=lat0, lon0=lon0, dlat=dlat, dlon=dlon, rows=rows, cols=cols, scale=scale
        )

    def undulation(self, lat: float, lon: float) -> float | None:
        """N at (lat, lon) in metres, or None outside the grid."""
        y = (lat - self.lat0) / self.dlat
        x = ((lon - self.lon0) % 360.0) / self.dlon
        if not 0.0 <= y <= self.rows - 1:
            return None
        row = min(int(y), self.rows - 2)
        col = int(x)
        if col >= self.cols - 1 and not self._wraps:
            if x > self.cols - 1 + 1e-9:
                return None
            col = self.cols - 2
        east = (col + 1) % self.cols
        fy, fx = y - row, x - col
        v, width = self._values, self.cols
        sw, se = v[row * width + col], v[row * width + east]
        nw, ne = v[(row + 1) * width + col], v[(row + 1) * width + east]
        value = (
            (sw * (1 - fx) + se * fx) * (1 - fy) + (nw * (1 - fx) + ne * fx) * fy
        ) * self._scale
        return None if math.isnan(value) or abs(value) > 1000.0 else float(value)


@cache
def bundled_geoid() -> GeoidGrid:
    """The 30' EGM96 grid shipped with the gateway (decoded once, on first use)."""
    data = (DATA_DIR / _BUNDLED_NAME).read_bytes()
    return GeoidGrid.from_bundled(data)
