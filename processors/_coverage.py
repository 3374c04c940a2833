"""A coverage (lawnmower) pattern over an order's area; pure, no I/O.

The sensor is a nadir camera whose cross-track field of view is ``hfov_deg``: flown at
``height_agl_m`` it sees a swath ``2 h tan(hfov / 2)`` wide. ``lawnmower`` lays parallel
lines across the area, along its longest edge, ``swath × (1 - overlap)`` apart, the first
and last half a spacing inside its edges, and flies them back and forth. Each line runs the
whole width of the area within its swath (not only where the line itself crosses it), so
the swaths cover the area's slanted edges too.

The area is laid in a local plane (equirectangular about its centre: within 0.1 % over the
tens of kilometres an order's area spans) for the pattern; the waypoints come back as
latitude and longitude.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["Survey", "lawnmower", "swath_m"]

LatLon = tuple[float, float]
_M_PER_DEG = 111_320.0


@dataclass(frozen=True, slots=True)
class Survey:
    """The survey's turn points (two per line, in flying order) and its swath width (m)."""

    points: tuple[LatLon, ...]
    swath_m: float
    spacing_m: float
    lines: int


def swath_m(height_agl_m: float, hfov_deg: float) -> float:
    """The ground width a nadir camera of ``hfov_deg`` sees from ``height_agl_m``."""
    return 2.0 * height_agl_m * math.tan(math.radians(hfov_deg) / 2.0)


def _band_extent(
    xy: Sequence[tuple[float, float]], low: float, high: float
) -> tuple[float, float] | None:
    """The x extent of the polygon ``xy`` between y = ``low`` and y = ``high``."""
    xs = [x for x, y in xy if low <= y <= high]
    for (x1, y1), (x2, y2) in zip(xy, (*xy[1:], xy[0]), strict=True):
        for edge_y in (low, high):
            if (y1 - edge_y) * (y2 - edge_y) < 0:
                xs.append(x1 + (edge_y - y1) / (y2 - y1) * (x2 - x1))
    return (min(xs), max(xs)) if xs else None


def lawnmower(
    corners: Sequence[LatLon],
    *,
    height_agl_m: float,
    hfov_deg: float,
    overlap: float,
    max_lines: int,
) -> Survey | str:
    """The survey of the polygon ``corners`` (see the module docstring), or why there is none."""
    width = swath_m(height_agl_m, hfov_deg)
    spacing = width * (1.0 - overlap)
    lat0 = sum(c[0] for c in corners) / len(corners)
    lon0 = corners[0][1]
    scale = math.cos(math.radians(lat0)) * _M_PER_DEG

    def to_xy(point: LatLon) -> tuple[float, float]:
        dlon = (point[1] - lon0 + 180.0) % 360.0 - 180.0
        return dlon * scale, (point[0] - lat0) * _M_PER_DEG

    plane = [to_xy(c) for c in corners]
    # Lines along the longest edge: fewest turns for a long, thin area.
    edges = zip(plane, (*plane[1:], plane[0]), strict=True)
    (ax, ay), (bx, by) = max(edges, key=lambda e: math.dist(e[0], e[1]))
    angle = math.atan2(by - ay, bx - ax)
    cos_a, sin_a = math.cos(angle), math.sin(angle)
    turned = [(x * cos_a + y * sin_a, -x * sin_a + y * cos_a) for x, y in plane]
    low = min(y for _, y in turned)
    depth = max(y for _, y in turned) - low
    lines = max(1, math.ceil(depth / spacing))
    if lines > max_lines:
        return (
            f"the survey needs {lines} lines {spacing:.0f} m apart (swath {width:.0f} m at"
            f" {height_agl_m:.0f} m above ground); at most {max_lines} are flown"
        )
    points: list[LatLon] = []
    for i in range(lines):
        y = low + (i + 0.5) * depth / lines
        extent = _band_extent(turned, y - width / 2.0, y + width / 2.0)
        if extent is None:  # a band the polygon does not reach (cannot happen inside it)
            continue
        ends = extent if i % 2 == 0 else extent[::-1]
        for x in ends:
            east, north = x * cos_a - y * sin_a, x * sin_a + y * cos_a
            lon = (lon0 + east / scale + 180.0) % 360.0 - 180.0
            points.append((lat0 + north / _M_PER_DEG, lon))
    return Survey(tuple(points), width, depth / lines, lines)
