"""Geodesy on WGS 84: geodesic distance and bearing, and MGRS grid references.

Distances come from geographiclib (Karney's geodesics, accurate to nanometres). MGRS uses the
``mgrs`` package (GeoTrans), which *truncates* when encoding and decodes to the *centre* of
the cell, so a decoded reference carries an uncertainty of half the cell's diagonal. The
polar caps (north of 84° N, south of 80° S) use UPS, which this gateway refuses with a clear
error: no C2 system we feed uses polar MGRS, and a silent UPS string would confuse one.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal

import mgrs  # type: ignore[import-untyped]
from geographiclib.geodesic import Geodesic  # type: ignore[import-untyped]

from gateway.errors import GatewayError

__all__ = [
    "MgrsError",
    "MgrsPrecision",
    "MgrsRef",
    "destination",
    "distance_bearing",
    "from_mgrs",
    "to_mgrs",
]

MgrsPrecision = Literal[1, 10, 100]
_DIGITS: dict[int, int] = {1: 5, 10: 4, 100: 3}
_UTM_NORTH_LIMIT = 84.0
_UTM_SOUTH_LIMIT = -80.0
_CONVERTER = mgrs.MGRS()
_PATTERN = re.compile(r"^(\d{1,2})([C-HJ-NP-X])([A-HJ-NP-Z]{2})(\d{0,10})$")


class MgrsError(GatewayError, ValueError):
    """Raised for a position MGRS cannot express here (polar) or a malformed reference."""


@dataclass(frozen=True, slots=True)
class MgrsRef:
    """A decoded MGRS reference: the cell centre and how far the true point may be from it."""

    lat_deg: float
    lon_deg: float
    precision_m: int
    uncertainty_m: float


def distance_bearing(lat1: float, lon1: float, lat2: float, lon2: float) -> tuple[float, float]:
    """Geodesic distance (m) and initial bearing (degrees from true north, 0..360)."""
    line = Geodesic.WGS84.Inverse(lat1, lon1, lat2, lon2)
    return float(line["s12"]), float(line["azi1"]) % 360.0


def destination(
    lat: float, lon: float, bearing_deg: float, distance_m: float
) -> tuple[float, float]:
    """The point ``distance_m`` from (lat, lon) along the geodesic starting at ``bearing_deg``."""
    line = Geodesic.WGS84.Direct(lat, lon, bearing_deg, distance_m)
    return float(line["lat2"]), float(line["lon2"])


def to_mgrs(lat: float, lon: float, precision_m: MgrsPrecision = 1, *, spaced: bool = False) -> str:
    """The MGRS reference of (lat, lon) at 1, 10 or 100 m, truncated as MGRS requires.

    Raises ``MgrsError`` in the UPS polar areas and for coordinates off the globe.
    """
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0) or math.isnan(lat + lon):
        raise MgrsError(f"not a position: lat {lat}, lon {lon}")
    if lat > _UTM_NORTH_LIMIT or lat < _UTM_SOUTH_LIMIT:
        raise MgrsError(
            f"lat {lat:.5f} is in a polar (UPS) area; MGRS here covers 80 S to 84 N only"
        )
    if precision_m not in _DIGITS:
        raise MgrsError(f"precision must be 1, 10 or 100 m, found {precision_m}")
    text = str(_CONVERTER.toMGRS(lat, min(lon, 179.9999999999), MGRSPrecision=_DIGITS[precision_m]))
    if not spaced:
        return text
    match = _PATTERN.match(text)
    assert match is not None  # noqa: S101 - mgrs output always matches
    zone, band, square, digits = match.groups()
    half = len(digits) // 2
    return f"{zone}{band} {square} {digits[:half]} {digits[half:]}"


def from_mgrs(text: str) -> MgrsRef:
    """Decode an MGRS reference (spaces and lower case accepted) to its cell centre."""
    compact = re.sub(r"\s+", "", text).upper()
    match = _PATTERN.match(compact)
    if match is None or len(match.group(4)) % 2:
        raise MgrsError(f"not an MGRS reference: {text!r}")
    digits = len(match.group(4)) // 2
    if digits not in (3, 4, 5):
        raise MgrsError(f"expected 3 to 5 digits each for easting and northing in {text!r}")
    try:
        lat, lon = _CONVERTER.toLatLon(compact)
    except Exception as exc:
        raise MgrsError(f"not a valid MGRS reference: {text!r}") from exc
    precision = 10 ** (5 - digits)
    return MgrsRef(float(lat), float(lon), precision, precision * math.sqrt(2) / 2)
