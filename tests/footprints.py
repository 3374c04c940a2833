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
    area: Sequence[LatLon], waypoints: Sequence[LatLon], swath_m: float, raster_m: float = 10.0
) -> float:
    """The fraction of ``area`` inside the footprints swept between consecutive waypoints."""
    centre = (sum(p[0] for p in area) / len(area), sum(p[1] for p in area) / len(area))
    polygon = _plane(centre, area)
    legs = list(pairwise(_plane(centre, waypoints)))
    try:
        from shapely.geometry import LineString, Polygon
        from shapely.ops import unary_union
    except ImportError:
        return _raster(polygon, legs, swath_m, raster_m)
    seen = unary_union([LineString(leg).buffer(swath_m / 2, cap_style="flat") for leg in legs])
    shape = Polygon(polygon)
    return float(shape.intersection(seen).area / shape.area)


def _inside(point: tuple[float, float], polygon: Sequence[tuple[float, float]]) -> bool:
    x, y = point
    inside = False
    for (x1, y1), (x2, y2) in zip(polygon, (*polygon[1:], polygon[0]), strict=True):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) / (y2 - y1) * (x2 - x1):
            inside = not inside
    return inside


def _near_leg(
    point: tuple[float, float], leg: tuple[tuple[float, float], ...], half: float
) -> bool:
    (x1, y1), (x2, y2) = leg
    dx, dy = x2 - x1, y2 - y1
    length2 = dx * dx + dy * dy
    if length2 == 0:
        return False
    t = ((point[0] - x1) * dx + (point[1] - y1) * dy) / length2
    if not 0 <= t <= 1:
        return False
    return abs((point[0] - x1) * dy - (point[1] - y1) * dx) / math.sqrt(length2) <= half


def _raster(
    polygon: Sequence[tuple[float, float]],
    legs: Sequence[tuple[tuple[float, float], ...]],
    swath_m: float,
    cell_m: float,
) -> float:
    xs, ys = [p[0] for p in polygon], [p[1] for p in polygon]
    total = seen = 0
    y = min(ys) + cell_m / 2
    while y < max(ys):
        x = min(xs) + cell_m / 2
        while x < max(xs):
            if _inside((x, y), polygon):
                total += 1
                seen += any(_near_leg((x, y), leg, swath_m / 2) for leg in legs)
            x += cell_m
        y += cell_m
    return seen / total
