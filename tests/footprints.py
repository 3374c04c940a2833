"""The ground a survey's camera sees: the union of its planned footprints, computed here.

Independent of the planner (``processors._coverage``): the waypoints are laid on an azimuthal
equidistant plane about the area's centre with geographiclib, each leg between two waypoints
is swept by a footprint ``swath_m`` wide (a flat-ended strip), and the union of the strips is
intersected with the area. With shapely installed the union is exact; without, a raster of
``raster_m`` cells approximates it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from itertools import pairwise

import numpy as np
from geographiclib.geodesic import Geodesic

__all__ = ["covered_fraction"]

LatLon = tuple[float, float]


def _plane(centre: LatLon, points: Sequence[LatLon]) -> list[tuple[float, float]]:
    out = []
    for lat, lon in points:
        g = Geodesic.WGS84.Inverse(centre[0], centre[1], lat, lon)
        azimuth = math.radians(g["azi1"])
        out.append((g["s12"] * math.sin(azimuth), g["s12"] * math.cos(azimuth)))
    return out


def covered_fraction(
    area: Sequence[LatLon],
    waypoints: Sequence[LatLon],
    swath_m: float,
    raster_m: float = 10.0,
    *,
    exact: bool = True,
) -> float:
    """The fraction of ``area`` inside the footprints swept between consecutive waypoints
    (``exact``: with shapely when it is installed; else on the raster)."""
    centre = (sum(p[0] for p in area) / len(area), sum(p[1] for p in area) / len(area))
    polygon = _plane(centre, area)
    legs = list(pairwise(_plane(centre, waypoints)))
    try:
        from shapely.geometry import LineString, Polygon
        from shapely.ops import unary_union
    except ImportError:
        exact = False
    if not exact:
        return _raster(polygon, legs, swath_m, raster_m)
    seen = unary_union([LineString(leg).buffer(swath_m / 2, cap_style="flat") for leg in legs])
    shape = Polygon(polygon)
    return float(shape.intersection(seen).area / shape.area)


def _raster(
    polygon: Sequence[tuple[float, float]],
    legs: Sequence[tuple[tuple[float, float], ...]],
    swath_m: float,
    cell_m: float,
) -> float:
    """The covered fraction on a raster: cells of ``cell_m`` (coarser for a large area, at
    most about 250 × 250 cells), each counted by its centre."""
    xs = np.array([p[0] for p in polygon])
    ys = np.array([p[1] for p in polygon])
    cell_m = max(cell_m, float(max(np.ptp(xs), np.ptp(ys))) / 250.0)
    gx, gy = np.meshgrid(
        np.arange(xs.min() + cell_m / 2, xs.max(), cell_m),
        np.arange(ys.min() + cell_m / 2, ys.max(), cell_m),
    )
    px, py = gx.ravel(), gy.ravel()
    inside = np.zeros(px.shape, dtype=bool)
    for (x1, y1), (x2, y2) in zip(polygon, (*polygon[1:], polygon[0]), strict=True):
        if y1 == y2:
            continue
        crosses = (y1 > py) != (y2 > py)
        inside ^= crosses & (px < x1 + (py - y1) / (y2 - y1) * (x2 - x1))
    seen = np.zeros(px.shape, dtype=bool)
    for (x1, y1), (x2, y2) in legs:
        dx, dy = x2 - x1, y2 - y1
        length = math.hypot(dx, dy)
        if length == 0:
            continue
        along = ((px - x1) * dx + (py - y1) * dy) / length
        across = np.abs((px - x1) * dy - (py - y1) * dx) / length
        seen |= (along >= 0) & (along <= length) & (across <= swath_m / 2)
    return float(np.count_nonzero(seen & inside) / np.count_nonzero(inside))
