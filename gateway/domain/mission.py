"""Reconnaissance routes as MAVLink mission items, and the plane geometry of a geofence.

A ``MissionItem`` is one MAVLink mission item in the global frame (altitudes MSL), the
vocabulary the orders processor and the airframe side share: the processor builds them
from an order, the fleet uploads them (MISSION_COUNT / MISSION_ITEM_INT / MISSION_ACK).
Only navigation commands are built here (waypoint, timed loiter): nothing arms or releases.

The geofence is a polygon of (lat, lon) corners. ``inside`` and ``crosses`` work in a local
equirectangular plane around the fence, which is exact enough for fences of tens of
kilometres (the error is far below a GNSS fix); a route is inside when each of its points is
inside and none of its legs crosses an edge.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise

from gateway.domain.geodesy import distance_bearing

__all__ = [
    "MAV_CMD_DO_SET_MODE",
    "MAV_CMD_MISSION_START",
    "MAV_CMD_NAV_LOITER_TIME",
    "MAV_CMD_NAV_RETURN_TO_LAUNCH",
    "MAV_CMD_NAV_WAYPOINT",
    "MissionItem",
    "Outcome",
    "crosses",
    "inside",
    "polygon_problem",
    "route_inside",
    "route_length_m",
]

MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_NAV_LOITER_TIME = 19
MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_MISSION_START = 300
#: MAV_FRAME_GLOBAL: latitude, longitude, altitude above mean sea level.
MAV_FRAME_GLOBAL = 0

LatLon = tuple[float, float]


@dataclass(frozen=True, slots=True)
class MissionItem:
    """One mission item: a navigation ``command`` at a point, altitude in metres MSL."""

    command: int
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    frame: int = MAV_FRAME_GLOBAL


@dataclass(frozen=True, slots=True)
class Outcome:
    """How one exchange with an airframe ended: ``ok``, or why not, after ``attempts``."""

    ok: bool
    detail: str
    attempts: int = 1


def route_length_m(points: Sequence[LatLon]) -> float:
    """The geodesic length (m) of the legs through ``points`` in order."""
    return sum(distance_bearing(a[0], a[1], b[0], b[1])[0] for a, b in pairwise(points))


def _plane(fence: Sequence[LatLon]) -> tuple[float, float, float]:
    lat0 = sum(p[0] for p in fence) / len(fence)
    # Longitudes averaged as offsets from the first corner: a fence across the antimeridian
    # (179° and -179°) is centred on 180°, not on 0° (which turned it inside out).
    ref = fence[0][1]
    lon0 = ref + sum((p[1] - ref + 180.0) % 360.0 - 180.0 for p in fence) / len(fence)
    return lat0, lon0, math.cos(math.radians(lat0))


def _xy(point: LatLon, plane: tuple[float, float, float]) -> tuple[float, float]:
    lat0, lon0, scale = plane
    # Longitudes wrap: a fence near the antimeridian keeps its points on one side.
    dlon = (point[1] - lon0 + 180.0) % 360.0 - 180.0
    return dlon * scale, point[0] - lat0


def inside(fence: Sequence[LatLon], point: LatLon) -> bool:
    """True if ``point`` is inside the polygon ``fence`` (3+ corners; on an edge is inside)."""
    if len(fence) < 3:
        raise ValueError(f"a geofence needs at least 3 corners, found {len(fence)}")
    plane = _plane(fence)
    x, y = _xy(point, plane)
    corners = [_xy(c, plane) for c in fence]
    is_in = False
    for (x1, y1), (x2, y2) in zip(corners, corners[1:] + corners[:1], strict=True):
        if _on_segment((x, y), (x1, y1), (x2, y2)):
            return True
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            is_in = not is_in
    return is_in


def _cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _on_segment(p: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> bool:
    if abs(_cross(a, b, p)) > 1e-12:
        return False
    return min(a[0], b[0]) - 1e-12 <= p[0] <= max(a[0], b[0]) + 1e-12 and (
        min(a[1], b[1]) - 1e-12 <= p[1] <= max(a[1], b[1]) + 1e-12
    )


def crosses(fence: Sequence[LatLon], a: LatLon, b: LatLon) -> bool:
    """True if the leg from ``a`` to ``b`` properly crosses an edge of ``fence``."""
    plane = _plane(fence)
    p, q = _xy(a, plane), _xy(b, plane)
    corners = [_xy(c, plane) for c in fence]
    for c1, c2 in zip(corners, corners[1:] + corners[:1], strict=True):
        d1, d2 = _cross(c1, c2, p), _cross(c1, c2, q)
        d3, d4 = _cross(p, q, c1), _cross(p, q, c2)
        if d1 * d2 < 0 and d3 * d4 < 0:
            return True
    return False


def route_inside(fence: Sequence[LatLon], points: Sequence[LatLon]) -> LatLon | None:
    """None if the route through ``points`` stays in ``fence``; else the first point outside
    (or, for a leg that leaves and comes back, the leg's start)."""
    for point in points:
        if not inside(fence, point):
            return point
    for a, b in pairwise(points):
        if crosses(fence, a, b):
            return a
    return None


def polygon_problem(corners: Sequence[LatLon]) -> str | None:
    """Why ``corners`` is not a simple polygon (a repeated corner, no area, edges that cross),
    or None. Corners are 1-based in the answer, as an operator counts them."""
    plane = _plane(corners)
    pts = [_xy(c, plane) for c in corners]
    n = len(pts)
    edges = list(zip(pts, pts[1:] + pts[:1], strict=True))
    for i, (a, b) in enumerate(edges):
        if math.hypot(b[0] - a[0], b[1] - a[1]) < 1e-9:
            return f"has corners {i + 1} and {(i + 1) % n + 1} at the same point"
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue  # adjacent through the closing edge
            (p, q), (c1, c2) = edges[i], edges[j]
            d1, d2 = _cross(c1, c2, p), _cross(c1, c2, q)
            d3, d4 = _cross(p, q, c1), _cross(p, q, c2)
            if d1 * d2 < 0 and d3 * d4 < 0:
                return (
                    f"crosses itself: edge {i + 1}-{i + 2} crosses edge {j + 1}-{(j + 1) % n + 1}"
                )
    area = sum(a[0] * b[1] - b[0] * a[1] for a, b in edges) / 2.0
    if abs(area) < 1e-12:
        return "has no area (its corners are on one line)"
    return None
