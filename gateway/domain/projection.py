"""Map projections for DEM grids: transverse Mercator (SWEREF 99, UTM, TM35FIN) by EPSG code.

National elevation grids are delivered in projected coordinates, not latitude and longitude:
Lantmäteriet's in SWEREF 99 TM (EPSG:3006) or the local SWEREF 99 zones (EPSG:3007–3018),
Finland's in ETRS-TM35FIN (EPSG:3067), Norway's in ETRS89 / UTM (EPSG:258xx). All of them are
transverse Mercator, so one implementation of the forward projection covers them. It uses
Krüger's series to fourth order in n, as in Lantmäteriet's "Gauss conformal projection"
formulas, which is accurate to well under a millimetre inside a zone: far below any DEM's
error. Only the forward direction (lat, lon → easting, northing) is needed to look a point up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gateway.errors import GatewayError

__all__ = [
    "GEOGRAPHIC",
    "Geographic",
    "ProjectionError",
    "TransverseMercator",
    "crs_from_epsg",
]

_GRS80 = (6_378_137.0, 1 / 298.257222101)
_WGS84 = (6_378_137.0, 1 / 298.257223563)
# SWEREF 99 local zones (EPSG:3007–3018): central meridian in degrees, scale 1, FE 150 km.
_SWEREF99_LOCAL = {
    3007: 12.0,
    3008: 13.5,
    3009: 15.0,
    3010: 16.5,
    3011: 18.0,
    3012: 14.25,
    3013: 15.75,
    3014: 17.25,
    3015: 18.75,
    3016: 20.25,
    3017: 21.75,
    3018: 23.25,
}
# Geographic CRSs whose differences from WGS 84 (under a metre in Europe) are far below a DEM
# cell: WGS 84, ETRS89 and SWEREF 99.
_GEOGRAPHIC_EPSG = frozenset({4326, 4258, 4619})


_MAX_DLON_DEG = 45.0


class ProjectionError(GatewayError, ValueError):
    """Raised for a coordinate reference system this module cannot project to."""


@dataclass(frozen=True, slots=True)
class Geographic:
    """Latitude and longitude in degrees: the identity projection, x = lon and y = lat."""

    epsg: int = 4326

    def forward(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """(x, y) = (lon, lat) in degrees."""
        return lon_deg, lat_deg


GEOGRAPHIC = Geographic()


class TransverseMercator:
    """A transverse Mercator projection on an ellipsoid (Krüger series, 4th order)."""

    __slots__ = (
        "_a_hat",
        "_beta",
        "_e2",
        "epsg",
        "false_easting_m",
        "false_northing_m",
        "k0",
        "lon0_deg",
    )

    def __init__(
        self,
        *,
        epsg: int,
        lon0_deg: float,
        k0: float,
        false_easting_m: float,
        false_northing_m: float = 0.0,
        ellipsoid: tuple[float, float] = _GRS80,
    ) -> None:
        a, f = ellipsoid
        self.epsg = epsg
        self.lon0_deg = lon0_deg
        self.k0 = k0
        self.false_easting_m = false_easting_m
        self.false_northing_m = false_northing_m
        self._e2 = f * (2 - f)
        n = f / (2 - f)
        self._a_hat = a / (1 + n) * (1 + n**2 / 4 + n**4 / 64)
        self._beta = (
            n / 2 - 2 * n**2 / 3 + 5 * n**3 / 16 + 41 * n**4 / 180,
            13 * n**2 / 48 - 3 * n**3 / 5 + 557 * n**4 / 1440,
            61 * n**3 / 240 - 103 * n**4 / 140,
            49561 * n**4 / 161280,
        )

    def __repr__(self) -> str:
        return f"TransverseMercator(epsg={self.epsg}, lon0_deg={self.lon0_deg})"

    def forward(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """(easting, northing) in metres of a point given in degrees.

        Points more than 45° of longitude from the central meridian, where the series no
        longer holds and no grid in this projection lies, give (nan, nan).
        """
        dlon_deg = (lon_deg - self.lon0_deg + 180.0) % 360.0 - 180.0
        if not abs(dlon_deg) <= _MAX_DLON_DEG:
            return math.nan, math.nan
        e2 = self._e2
        phi = math.radians(lat_deg)
        dlon = math.radians(dlon_deg)
        s = math.sin(phi)
        # Conformal latitude by the series in e² (Lantmäteriet's A, B, C, D).
        a_ = e2
        b_ = (5 * e2**2 - e2**3) / 6
        c_ = (104 * e2**3 - 45 * e2**4) / 120
        d_ = 1237 * e2**4 / 1260
        phi_c = phi - s * math.cos(phi) * (a_ + b_ * s**2 + c_ * s**4 + d_ * s**6)
        xi = math.atan2(math.tan(phi_c), math.cos(dlon))
        eta = math.atanh(math.cos(phi_c) * math.sin(dlon))
        north = xi
        east = eta
        for j, beta in enumerate(self._beta, start=1):
            north += beta * math.sin(2 * j * xi) * math.cosh(2 * j * eta)
            east += beta * math.cos(2 * j * xi) * math.sinh(2 * j * eta)
        scale = self.k0 * self._a_hat
        return scale * east + self.false_easting_m, scale * north + self.false_northing_m


def crs_from_epsg(epsg: int) -> Geographic | TransverseMercator:
    """The projection for an EPSG code of a DEM grid; ``ProjectionError`` names unknown codes.

    Known: 4326/4258/4619 (geographic), 3006 (SWEREF 99 TM), 3007–3018 (SWEREF 99 local
    zones), 3067 (ETRS-TM35FIN), 25828–25838 (ETRS89 / UTM), 32601–32660 and 32701–32760
    (WGS 84 / UTM north and south).
    """
    if epsg in _GEOGRAPHIC_EPSG:
        return Geographic(epsg)
    if epsg == 3006:
        return TransverseMercator(epsg=epsg, lon0_deg=15.0, k0=0.9996, false_easting_m=5e5)
    if epsg in _SWEREF99_LOCAL:
        lon0 = _SWEREF99_LOCAL[epsg]
        return TransverseMercator(epsg=epsg, lon0_deg=lon0, k0=1.0, false_easting_m=1.5e5)
    if epsg == 3067:
        return TransverseMercator(epsg=epsg, lon0_deg=27.0, k0=0.9996, false_easting_m=5e5)
    if 25828 <= epsg <= 25838:
        return _utm(epsg, epsg - 25800, south=False, ellipsoid=_GRS80)
    if 32601 <= epsg <= 32660:
        return _utm(epsg, epsg - 32600, south=False, ellipsoid=_WGS84)
    if 32701 <= epsg <= 32760:
        return _utm(epsg, epsg - 32700, south=True, ellipsoid=_WGS84)
    raise ProjectionError(
        f"EPSG:{epsg} is not supported for DEM grids; use geographic (4326), SWEREF 99 "
        "(3006–3018), ETRS-TM35FIN (3067) or UTM (258xx, 326xx, 327xx)"
    )


def _utm(
    epsg: int, zone: int, *, south: bool, ellipsoid: tuple[float, float]
) -> TransverseMercator:
    return TransverseMercator(
        epsg=epsg,
        lon0_deg=6.0 * zone - 183.0,
        k0=0.9996,
        false_easting_m=5e5,
        false_northing_m=1e7 if south else 0.0,
        ellipsoid=ellipsoid,
    )
