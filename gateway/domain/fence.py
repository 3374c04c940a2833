"""Geofence geometry on the WGS 84 ellipsoid: a fence's edges are geodesics.

A fence is a polygon of (lat, lon) corners, and the edge between two corners is the
**geodesic** (the shortest path on the ellipsoid) between them, as airspace boundaries are
read unless stated otherwise. It is *not* the parallel or the meridian through them: the
edge from (65° N, 20° E) to (65° N, 24° E) bows 1.5 km north of 65° N at 22° E. A fence
meant to follow a parallel needs corners along it (a corner every 20 km keeps the bow under
20 m at 67° N).

The tests are planar, in an **ellipsoidal gnomonic projection** centred on the fence
(Karney 2013, "Algorithms for geodesics", section 8: x, y = ρ sin α₀, ρ cos α₀ with
ρ = m₁₂/M₁₂ from geographiclib's inverse problem). In it every geodesic is a straight line
on a sphere and very nearly one on the ellipsoid: measured against geographiclib's own
geodesics, a geodesic between two points within 300 km of the centre is straight to 0.013 m,
within 500 km to 0.1 m, within 1000 km to 1.6 m. A fence must fit within ``MAX_RADIUS_M``
(1000 km) of its centre; its own edges are then straight to under 2 m, and a leg between two
points inside it is a straight segment too. So point-in-polygon and edge crossing are exact
plane tests, with no sampling, and fences across the antimeridian need no special case (the
projection is computed from geodesics, not from longitudes).

Distances outside the fence are measured in the plane and scaled back by the projection's
azimuthal scale at the point (``M₁₂``); the radial scale differs by a further factor ``M₁₂``,
so a distance is good to 0.1 % within 300 km of the centre, 1.3 % at 1000 km.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise

from geographiclib.geodesic import Geodesic  # type: ignore[import-untyped]

from gateway.errors import GatewayError

__all__ = [
    "MAX_RADIUS_M",
    "ON_EDGE_M",
    "Fence",
    "FenceError",
    "Gnomonic",
    "fence_of",
    "segment_distance",
]

LatLon = tuple[float, float]
XY = tuple[float, float]

#: How far from its centre a fence may reach (see the module docstring for why).
MAX_RADIUS_M = 1_000_000.0
#: A point this close to an edge is on it, and on the edge is inside.
ON_EDGE_M = 0.01
_MASK = Geodesic.AZIMUTH | Geodesic.REDUCEDLENGTH | Geodesic.GEODESICSCALE
_GEOD = Geodesic.WGS84


class FenceError(GatewayError, ValueError):
    """Raised for corners that are not a fence this module can check (fewer than 3, too big)."""


@dataclass(frozen=True, slots=True)
class Gnomonic:
    """The ellipsoidal gnomonic projection centred on (``lat0``, ``lon0``), in metres."""

    lat0: float
    lon0: float

    def forward(self, point: LatLon) -> tuple[float, float, float] | None:
        """(x, y, scale) of ``point``, or None beyond the projection's horizon (about 90°
        from the centre). ``scale`` is M₁₂: a plane distance times it is metres on the
        ground, near the point."""
        got = _GEOD.Inverse(self.lat0, self.lon0, point[0], point[1], _MASK)
        scale = float(got["M12"])
        if scale <= 1e-3:
            return None
        rho = float(got["m12"]) / scale
        azimuth = math.radians(float(got["azi1"]))
        return rho * math.sin(azimuth), rho * math.cos(azimuth), scale


def _centre(corners: Sequence[LatLon]) -> LatLon:
    """The corners' mean direction from the Earth's centre: across the antimeridian and
    round a pole as well as anywhere."""
    x = y = z = 0.0
    for lat, lon in corners:
        phi, lam = math.radians(lat), math.radians(lon)
        x += math.cos(phi) * math.cos(lam)
        y += math.cos(phi) * math.sin(lam)
        z += math.sin(phi)
    return math.degrees(math.atan2(z, math.hypot(x, y))), math.degrees(math.atan2(y, x))


def _cross(o: XY, a: XY, b: XY) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def segment_distance(p: XY, a: XY, b: XY) -> float:
    """Plane distance from ``p`` to the segment ``a``–``b``."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0.0 else ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / length2
    t = min(1.0, max(0.0, t))
    return math.hypot(p[0] - a[0] - t * dx, p[1] - a[1] - t * dy)


def _hits(p: XY, q: XY, a: XY, b: XY) -> list[float]:
    """Where along ``p``→``q`` (0..1) it meets the segment ``a``–``b``: a crossing, a touch,
    or both ends of an overlap."""
    r = (q[0] - p[0], q[1] - p[1])
    s = (b[0] - a[0], b[1] - a[1])
    denom = r[0] * s[1] - r[1] * s[0]
    ap = (a[0] - p[0], a[1] - p[1])
    rr = r[0] * r[0] + r[1] * r[1]
    if rr == 0.0:
        return []
    scale = math.sqrt(rr) * math.hypot(*s)
    if abs(denom) <= 1e-12 * scale:  # parallel: an overlap counts where it starts and ends
        if abs(ap[0] * r[1] - ap[1] * r[0]) > ON_EDGE_M * math.sqrt(rr):
            return []
        ta = (ap[0] * r[0] + ap[1] * r[1]) / rr
        tb = ((b[0] - p[0]) * r[0] + (b[1] - p[1]) * r[1]) / rr
        return [t for t in (ta, tb) if 0.0 < t < 1.0]
    t = (ap[0] * s[1] - ap[1] * s[0]) / denom
    u = (ap[0] * r[1] - ap[1] * r[0]) / denom
    slack = ON_EDGE_M / math.hypot(*s)
    if 0.0 < t < 1.0 and -slack <= u <= 1.0 + slack:
        return [t]
    return []


class Fence:
    """A fence's corners projected once; the plane tests of the module docstring."""

    __slots__ = ("corners", "edges", "plane", "xy")

    def __init__(self, corners: Sequence[LatLon]) -> None:
        if len(corners) < 3:
            raise FenceError(f"a geofence needs at least 3 corners, found {len(corners)}")
        self.corners = tuple(corners)
        self.plane = Gnomonic(*_centre(self.corners))
        xy: list[XY] = []
        for i, corner in enumerate(self.corners):
            got = self.plane.forward(corner)
            if got is None or math.hypot(got[0], got[1]) * got[2] > MAX_RADIUS_M:
                raise FenceError(
                    f"reaches more than {MAX_RADIUS_M / 1000:.0f} km from its centre at"
                    f" corner {i + 1}; split it into smaller ones"
                )
            xy.append((got[0], got[1]))
        self.xy = tuple(xy)
        self.edges = tuple(zip(self.xy, self.xy[1:] + self.xy[:1], strict=True))

    def project(self, point: LatLon) -> tuple[float, float, float] | None:
        """The point in the fence's plane (see ``Gnomonic.forward``)."""
        return self.plane.forward(point)

    def contains_xy(self, p: XY) -> bool:
        """True if the plane point ``p`` is inside (within ``ON_EDGE_M`` of an edge counts)."""
        is_in = False
        x, y = p
        for a, b in self.edges:
            if segment_distance(p, a, b) <= ON_EDGE_M:
                return True
            if (a[1] > y) != (b[1] > y) and x < a[0] + (y - a[1]) * (b[0] - a[0]) / (b[1] - a[1]):
                is_in = not is_in
        return is_in

    def contains(self, point: LatLon) -> bool:
        """True if ``point`` is inside the fence or on an edge."""
        got = self.project(point)
        return got is not None and self.contains_xy((got[0], got[1]))

    def boundary_xy(self, p: XY) -> float:
        """Plane distance from ``p`` to the nearest edge."""
        return min(segment_distance(p, a, b) for a, b in self.edges)

    def outside_m(self, point: LatLon) -> float:
        """How far ``point`` is outside the fence (m), 0 inside or on an edge."""
        got = self.project(point)
        if got is None:  # beyond the horizon: the nearest corner is a fair measure
            return min(
                float(_GEOD.Inverse(*point, *c, Geodesic.DISTANCE)["s12"]) for c in self.corners
            )
        p = (got[0], got[1])
        return 0.0 if self.contains_xy(p) else self.boundary_xy(p) * got[2]

    def crosses_edge(self, p: XY, q: XY) -> bool:
        """True if the plane segment ``p``→``q`` properly crosses an edge."""
        for a, b in self.edges:
            d1, d2 = _cross(a, b, p), _cross(a, b, q)
            d3, d4 = _cross(p, q, a), _cross(p, q, b)
            if d1 * d2 < 0 and d3 * d4 < 0:
                return True
        return False

    def segment_leaves(self, p: XY, q: XY) -> bool:
        """True if the plane segment ``p``→``q`` (both ends inside) goes outside between them:
        it is cut where it meets an edge, and each piece's middle must be inside."""
        cuts = sorted({0.0, 1.0, *(t for a, b in self.edges for t in _hits(p, q, a, b))})
        for t0, t1 in pairwise(cuts):
            t = (t0 + t1) / 2
            mid = (p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]))
            if not self.contains_xy(mid):
                return True
        return False


@functools.lru_cache(maxsize=64)
def fence_of(corners: tuple[LatLon, ...]) -> Fence:
    """The ``Fence`` of ``corners``, built once per fence (configured fences are few)."""
    return Fence(corners)
