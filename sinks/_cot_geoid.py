"""Geoid undulation from a PROJ ``.gtx`` grid (e.g. EGM96 15', Debian's proj-data package).

hae = MSL + N. The file is read once; nothing is downloaded. GTX layout: four big-endian
float64 (south-west latitude, longitude, latitude step, longitude step, degrees), two int32
(rows, columns), then rows of big-endian float32 from the south.
"""

from __future__ import annotations

import math
import struct
from array import array
from pathlib import Path

__all__ = ["GeoidGrid"]

_HEADER = struct.Struct(">ddddii")


class GeoidGrid:
    """Bilinear geoid undulation N (m) at a point."""

    def __init__(self, path: Path) -> None:
        data = path.read_bytes()
        if len(data) < _HEADER.size:
            raise ValueError(f"{path}: too short for a GTX grid")
        self.lat0, self.lon0, self.dlat, self.dlon, self.rows, self.cols = _HEADER.unpack_from(data)
        values = array("f")
        values.frombytes(data[_HEADER.size : _HEADER.size + 4 * self.rows * self.cols])
        if len(values) != self.rows * self.cols or self.dlat <= 0 or self.dlon <= 0:
            raise ValueError(f"{path}: header and size of the GTX grid disagree")
        values.byteswap()  # big-endian on disk
        self._values = values

    def undulation(self, lat: float, lon: float) -> float | None:
        """N at (lat, lon), or None outside the grid."""
        y = (lat - self.lat0) / self.dlat
        x = ((lon - self.lon0) % 360.0) / self.dlon
        if not (0 <= y <= self.rows - 1) or x > self.cols - 1 + 1e-9:
            return None
        row, col = min(int(y), self.rows - 2), min(int(x), self.cols - 2)
        fy, fx = y - row, x - col
        v = self._values
        base = row * self.cols + col
        sw, se = v[base], v[base + 1]
        nw, ne = v[base + self.cols], v[base + self.cols + 1]
        value = (sw * (1 - fx) + se * fx) * (1 - fy) + (nw * (1 - fx) + ne * fx) * fy
        return None if math.isnan(value) or abs(value) > 1000 else float(value)
