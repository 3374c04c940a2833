"""Short distances on WGS 84 as east/north metres: the tracker's local tangent plane.

``offset_m`` turns the difference between two nearby positions into east and north metres
with the ellipsoid's radii of curvature at their mid-latitude (meridian M, prime vertical N);
``displace`` is its inverse. Over the few kilometres a tracker gates and fuses across, the
error is far below any sensor's σ (second order in distance / Earth radius).

``GridPlane`` is one fixed plane for a whole theatre, used only to bucket tracks in a spatial
index: x = Δλ·N₀·cos φ₀, y = Δφ·M₀ about an origin. It distorts away from the origin's
latitude, so ``grid_radius_m`` converts a true radius into one that is certain to cover it
on the plane. It does not wrap at the antimeridian (a theatre never straddles it here).
"""

from __future__ import annotations

import math

__all__ = ["GridPlane", "displace", "offset_m"]

_A = 6_378_137.0
_F = 1 / 298.257223563
_E2 = _F * (2 - _F)


def _radii(lat_rad: float) -> tuple[float, float]:
    """Meridian and prime-vertical radii of curvature (m) at ``lat_rad``."""
    w2 = 1.0 - _E2 * math.sin(lat_rad) ** 2
    n = _A / math.sqrt(w2)
    return n * (1.0 - _E2) / w2, n


def _wrap_deg(dlon: float) -> float:
    return (dlon + 180.0) % 360.0 - 180.0


def offset_m(lat0: float, lon0: float, lat: float, lon: float) -> tuple[float, float]:
    """(east, north) metres from (lat0, lon0) to (lat, lon), both in degrees, when near."""
    mid = math.radians(0.5 * (lat0 + lat))
    m, n = _radii(mid)
    return (
        math.radians(_wrap_deg(lon - lon0)) * n * math.cos(mid),
        math.radians(lat - lat0) * m,
    )


def displace(lat: float, lon: float, east_m: float, north_m: float) -> tuple[float, float]:
    """The position (degrees) ``east_m``/``north_m`` from (lat, lon); inverse of ``offset_m``."""
    m, _ = _radii(math.radians(lat))
    lat2 = lat + math.degrees(north_m / m)
    mid = math.radians(0.5 * (lat + lat2))
    _, n = _radii(mid)
    lat2 = max(-90.0, min(90.0, lat2))
    lon2 = _wrap_deg(lon + math.degrees(east_m / (n * max(math.cos(mid), 1e-12))))
    return lat2, lon2


class GridPlane:
    """A fixed equirectangular plane about an origin, for bucketing positions in a grid."""

    def __init__(self, lat0: float, lon0: float) -> None:
        self.lat0 = lat0
        self.lon0 = lon0
        self._m0, n0 = _radii(math.radians(lat0))
        self._east0 = n0 * math.cos(math.radians(lat0))

    def forward(self, lat: float, lon: float) -> tuple[float, float]:
        """Plane (x, y) metres of (lat, lon)."""
        return (
            math.radians(_wrap_deg(lon - self.lon0)) * self._east0,
            math.radians(lat - self.lat0) * self._m0,
        )

    def grid_radius_m(self, lat: float, radius_m: float) -> float:
        """A plane radius certain to hold every point within ``radius_m`` (true) of latitude
        ``lat``: the true radius times the plane's largest stretch over that latitude band,
        with a little slack for the curvature the local formulas neglect.
        """
        m, _ = _radii(math.radians(lat))
        half_band = math.degrees(radius_m / m) * 1.01 + 1e-6
        lats = [lat - half_band, lat, lat + half_band]
        if lats[0] < 0.0 < lats[2]:
            lats.append(0.0)
        stretch = 0.0
        for phi in lats:
            phi_rad = math.radians(max(-89.999, min(89.999, phi)))
            m_phi, n_phi = _radii(phi_rad)
            stretch = max(stretch, self._m0 / m_phi, self._east0 / (n_phi * math.cos(phi_rad)))
        return radius_m * stretch * 1.001 + 1.0
