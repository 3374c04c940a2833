"""Reconnaissance routes as mission steps, and whether a route stays in a geofence.

A mission is a sequence of steps (``Waypoint``: fly to a point; ``Loiter``: circle a point
for a time), altitudes MSL: the vocabulary the orders processor and the airframe side
share. The processor builds them from an order; the fleet encodes them as MAVLink mission
items and uploads them (``gateway.fleet.missionitems``). ``ModeCommands`` names how the
fleet starts a mission and returns an airframe home (PX4 modes or plain MAVLink commands).
Only navigation steps exist here: nothing arms or releases.

The geofence is a polygon of (lat, lon) corners whose edges are geodesics; the geometry is
``gateway.domain.fence`` (an ellipsoidal gnomonic plane, where geodesics are straight). A
route is inside when each of its points is inside and each leg stays inside flown both as
the geodesic and as the rhumb line (``gateway.domain.paths``: what PX4 and ArduPilot fly
between two waypoints); ``route_exit`` says where and by how much it leaves.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Literal

from geographiclib.geodesic import Geodesic  # type: ignore[import-untyped]

from gateway.domain.fence import ON_EDGE_M, Fence, FenceError, fence_of
from gateway.domain.geodesy import distance_bearing
from gateway.domain.paths import rhumb_at, rhumb_bow_m, rhumb_points

__all__ = [
    "RHUMB_TOLERANCE_M",
    "Excursion",
    "Loiter",
    "MissionStep",
    "ModeCommands",
    "Outcome",
    "Waypoint",
    "crosses",
    "inside",
    "polygon_problem",
    "route_exit",
    "route_inside",
    "route_length_m",
]

ModeCommands = Literal["px4", "mavlink"]
"""How an airframe is told to start its mission and to return: ``px4``, PX4's AUTO.MISSION
and AUTO.RTL modes; ``mavlink``, the plain MISSION_START and NAV_RETURN_TO_LAUNCH commands."""

LatLon = tuple[float, float]
_GEOD = Geodesic.WGS84
#: Two corners closer than this (in the fence's plane, about metres) are one point.
_SAME_POINT_M = 1e-4


@dataclass(frozen=True, slots=True)
class Waypoint:
    """Fly to a point, altitude in metres MSL."""

    lat_deg: float
    lon_deg: float
    alt_msl_m: float


@dataclass(frozen=True, slots=True)
class Loiter:
    """Circle a point for ``seconds`` at ``radius_m``, altitude in metres MSL."""

    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    seconds: float
    radius_m: float


MissionStep = Waypoint | Loiter
"""One step of a mission."""


@dataclass(frozen=True, slots=True)
class Outcome:
    """How one exchange with an airframe ended: ``ok``, or why not, after ``attempts``."""

    ok: bool
    detail: str
    attempts: int = 1


def route_length_m(points: Sequence[LatLon]) -> float:
    """The geodesic length (m) of the legs through ``points`` in order."""
    return sum(distance_bearing(a[0], a[1], b[0], b[1])[0] for a, b in pairwise(points))


def inside(fence: Sequence[LatLon], point: LatLon) -> bool:
    """True if ``point`` is inside the polygon ``fence`` (3+ corners; on an edge is inside).
    Edges are geodesics (``gateway.domain.fence``)."""
    return fence_of(tuple(fence)).contains(point)


def crosses(fence: Sequence[LatLon], a: LatLon, b: LatLon) -> bool:
    """True if the geodesic from ``a`` to ``b`` properly crosses an edge of ``fence``."""
    plane = fence_of(tuple(fence))
    p, q = plane.project(a), plane.project(b)
    if p is None or q is None:
        return True
    return plane.crosses_edge((p[0], p[1]), (q[0], q[1]))


@dataclass(frozen=True, slots=True)
class Excursion:
    """Where a route leaves a fence: the farthest ``point`` outside found, how far outside
    (``outside_m``), and on which ``leg`` and ``path`` (``geodesic`` or ``rhumb line``);
    ``leg`` is None for a route point that is itself outside."""

    point: LatLon
    outside_m: float
    leg: tuple[LatLon, LatLon] | None = None
    path: str = ""


#: The rhumb line of a leg is checked when it parts from the geodesic by more than this,
#: along chords that depart from it by at most half of it.
RHUMB_TOLERANCE_M = 1.0
_WORST_SAMPLES = 128


def _worst(fence: Fence, leg: tuple[LatLon, LatLon], path: str) -> Excursion:
    """The farthest point outside ``fence`` along ``path`` of ``leg``: sampled, then refined
    round the farthest sample by golden section."""
    a, b = leg
    if path == "geodesic":
        line = _GEOD.InverseLine(a[0], a[1], b[0], b[1])

        def at(f: float) -> LatLon:
            got = line.Position(line.s13 * f)
            return float(got["lat2"]), float(got["lon2"])
    else:

        def at(f: float) -> LatLon:
            return rhumb_at(a, b, f)

    fs = [i / _WORST_SAMPLES for i in range(_WORST_SAMPLES + 1)]
    out = [fence.outside_m(at(f)) for f in fs]
    best = max(range(len(fs)), key=out.__getitem__)
    lo, hi = fs[max(0, best - 1)], fs[min(len(fs) - 1, best + 1)]
    ratio = (math.sqrt(5) - 1) / 2
    for _ in range(24):
        m1, m2 = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
        if fence.outside_m(at(m1)) >= fence.outside_m(at(m2)):
            hi = m2
        else:
            lo = m1
    f = (lo + hi) / 2
    far = fence.outside_m(at(f))
    if far < out[best]:
        f, far = fs[best], out[best]
    return Excursion(at(f), far, leg, path)


def route_exit(fence: Sequence[LatLon], points: Sequence[LatLon]) -> Excursion | None:
    """None if the route through ``points`` stays in ``fence``, else where it leaves.

    First every point (the first outside is named), then every leg, flown as the geodesic
    and as the rhumb line (``gateway.domain.paths``: what PX4 and ArduPilot fly): the
    geodesic is a straight line in the fence's plane, the rhumb line a chain of chords each
    within ``RHUMB_TOLERANCE_M`` / 2 of it. Of a leg that leaves, the farthest point
    outside on either path is named.
    """
    plane = fence_of(tuple(fence))
    xy: list[tuple[float, float, float]] = []
    for point in points:
        got = plane.project(point)
        if got is None or not plane.contains_xy((got[0], got[1])):
            return Excursion(point, plane.outside_m(point))
        xy.append(got)
    for (a, b), (pa, pb) in zip(pairwise(points), pairwise(xy), strict=True):
        leaves = ["geodesic"] if plane.segment_leaves(pa[:2], pb[:2]) else []
        length_m = math.hypot(pb[0] - pa[0], pb[1] - pa[1]) * min(pa[2], pb[2])
        if _rhumb_leaves(plane, (a, b), (pa[:2], pb[:2]), length_m):
            leaves.append("rhumb line")
        if leaves:  # the farther of the two paths that leave
            return max((_worst(plane, (a, b), path) for path in leaves), key=_outside)
    return None


def _outside(excursion: Excursion) -> float:
    return excursion.outside_m


def _rhumb_leaves(
    plane: Fence,
    leg: tuple[LatLon, LatLon],
    ends: tuple[tuple[float, float], tuple[float, float]],
    length_m: float,
) -> bool:
    """True if the rhumb line of ``leg`` (both ends inside) leaves the fence, checked along
    chords that are within ``RHUMB_TOLERANCE_M`` / 2 of it; False where it is within
    ``RHUMB_TOLERANCE_M`` of the geodesic (checked already)."""
    bow_m = rhumb_bow_m(*leg, length_m)
    if bow_m <= RHUMB_TOLERANCE_M:
        return False
    pieces = math.ceil(math.sqrt(2.0 * bow_m / RHUMB_TOLERANCE_M))
    chain = [ends[0]]
    for sample in rhumb_points(*leg, pieces)[1:-1]:
        got = plane.project(sample)
        if got is None or not plane.contains_xy((got[0], got[1])):
            return True
        chain.append((got[0], got[1]))
    chain.append(ends[1])
    return any(plane.segment_leaves(p, q) for p, q in pairwise(chain))


def route_inside(fence: Sequence[LatLon], points: Sequence[LatLon]) -> LatLon | None:
    """None if the route through ``points`` stays in ``fence``; else the first point outside
    or, for a leg that leaves and comes back, the leg's start (``route_exit`` says more)."""
    got = route_exit(fence, points)
    if got is None:
        return None
    return got.point if got.leg is None else got.leg[0]


def polygon_problem(corners: Sequence[LatLon]) -> str | None:
    """Why ``corners`` is not a simple polygon with geodesic edges (a repeated corner, no
    area, edges that cross, too big to check), or None. Corners are 1-based in the answer,
    as an operator counts them."""
    n = len(corners)
    if n < 3:
        return f"has {n} corners; at least 3 are needed"
    try:
        pts = list(Fence(corners).xy)
    except FenceError as exc:
        return str(exc)
    edges = list(zip(pts, pts[1:] + pts[:1], strict=True))
    for i, (a, b) in enumerate(edges):
        if math.hypot(b[0] - a[0], b[1] - a[1]) < _SAME_POINT_M:
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
    area = abs(sum(a[0] * b[1] - b[0] * a[1] for a, b in edges) / 2.0)
    perimeter = sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in edges)
    if 2.0 * area / perimeter < ON_EDGE_M:  # narrower on average than the edge tolerance
        return "has no area (its corners are on one line)"
    return None


def _cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
