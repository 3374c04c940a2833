"""Geodesy on WGS 84: geodesic distance and bearing, UTM zones, and MGRS grid references.

Distances come from geographiclib (Karney's geodesics, accurate to nanometres). MGRS uses the
``mgrs`` package (GeoTrans), which *truncates* when encoding (a reference names the cell the
point is in) and decodes to the *centre* of the cell, so a decoded reference carries an
uncertainty of half the cell's diagonal: 0.71 m at 1 m, 7.1 m at 10 m, 71 m at 100 m.

UTM zones follow the 6° rule with the Norway (32V widened west to 3° E) and Svalbard
(only 31X, 33X, 35X and 37X) exceptions; ``utm_zone`` states that rule in code, and the tests
check it against ``mgrs``. The polar caps (north of 84° N, south of 80° S) use UPS, which
this gateway refuses with ``MgrsError``: none of the C2 systems it feeds works there, and a
three-letter UPS reference would be misread by one expecting a zone number.
"""

from __future__ import annotations

import math
import re
import warnings
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
    "utm_zone",
]

MgrsPrecision = Literal[1, 10, 100]
_DIGITS: dict[int, int] = {1: 5, 10: 4, 100: 3}
_UTM_NORTH_LIMIT = 84.0
_UTM_SOUTH_LIMIT = -80.0
_BANDS = "CDEFGHJKLMNPQRSTUVWX"
_CONVERTER = mgrs.MGRS()
_PATTERN = re.compile(r"^(\d{1,2})([C-HJ-NP-X])([A-HJ-NP-Z]{2})(\d{0,10})$")
_UPS_PATTERN = re.compile(r"^[ABYZ][A-HJ-NP-Z]{2}\d*$")


class MgrsError(GatewayError, ValueError):
    """Raised for a position MGRS cannot express here (polar) or a malformed reference."""


@dataclass(frozen=True, slots=True)
class MgrsRef:
    """A decoded MGRS reference: the cell centre (degrees), the cell size and the uncertainty.

    ``uncertainty_m`` is half the cell's diagonal, the farthest the true point can be from
    the centre (plus a trace of grid scale factor).
    """

    lat_deg: float
    lon_deg: float
    precision_m: int
    uncertainty_m: float


def distance_bearing(lat1: float, lon1: float, lat2: float, lon2: float) -> tuple[float, float]:
    """Geodesic distance (m) and initial bearing (degrees clockwise from true north, 0–360)."""
    line = Geodesic.WGS84.Inverse(lat1, lon1, lat2, lon2)
    return float(line["s12"]), float(line["azi1"]) % 360.0


def destination(
    lat: float, lon: float, bearing_deg: float, distance_m: float
) -> tuple[float, float]:
    """(lat, lon) in degrees, ``distance_m`` metres from (lat, lon) along ``bearing_deg``."""
    line = Geodesic.WGS84.Direct(lat, lon, bearing_deg, distance_m)
    return float(line["lat2"]), float(line["lon2"])


def _check_utm_area(lat: float, lon: float) -> float:
    """``lon`` normalised to [−180, 180); ``MgrsError`` off the globe or in a UPS area."""
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise MgrsError(f"not a position: lat {lat}, lon {lon}")  # NaN fails the test too
    if lat > _UTM_NORTH_LIMIT or lat < _UTM_SOUTH_LIMIT:
        raise MgrsError(
            f"lat {lat:.5f} is in a polar (UPS) area; MGRS here covers 80° S to 84° N only"
        )
    # 180° E and 180° W are one meridian; MGRS puts it in zone 1, as mgrs does.
    return -180.0 if lon == 180.0 else lon


def utm_zone(lat: float, lon: float) -> tuple[int, str]:
    """The UTM zone number and latitude band letter of a point, with the Norway and
    Svalbard exceptions. ``MgrsError`` in the polar (UPS) areas.

    ``mgrs`` rounds coordinates (by up to about 1e-8°) before it picks a zone, so within a
    centimetre of a zone or band edge the two can disagree; ``to_mgrs`` always follows mgrs.
    """
    lon = _check_utm_area(lat, lon)
    band = _BANDS[min(int((lat + 80.0) // 8.0), len(_BANDS) - 1)]  # X stretches to 84° N
    # The modulo matters: 179.99999999999997 + 180 rounds to 360.0, which is zone 1 again.
    zone = int(((lon + 180.0) % 360.0) // 6.0) + 1
    if band == "V" and 3.0 <= lon < 12.0:
        zone = 32  # south-west Norway: 32V is widened west over the coast
    elif band == "X" and 0.0 <= lon < 42.0:
        # Svalbard: 32X, 34X and 36X do not exist; their neighbours are widened.
        zone = 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return zone, band


#: Latitudes this close south of the equator are written as the equator (about 1 cm).
_EQUATOR_SNAP_DEG = 1e-7


def _decodes(text: str) -> bool:
    try:
        _CONVERTER.toLatLon(text)
    except (mgrs.core.MGRSError, ValueError):
        return False
    return True


def to_mgrs(lat: float, lon: float, precision_m: MgrsPrecision = 1, *, spaced: bool = False) -> str:
    """The MGRS reference of a WGS 84 point at 1, 10 or 100 m, truncated as MGRS requires.

    ``spaced=True`` gives the display form ``33V WE 36308 74614``. Raises ``MgrsError`` in
    the polar (UPS) areas, for coordinates off the globe and for another precision.
    """
    lon = _check_utm_area(lat, lon)
    if precision_m not in _DIGITS:
        raise MgrsError(f"precision must be 1, 10 or 100 m, found {precision_m}")
    text = str(_CONVERTER.toMGRS(lat, lon, MGRSPrecision=_DIGITS[precision_m]))
    if -_EQUATOR_SNAP_DEG < lat < 0.0 and not _decodes(text):
        # Within a centimetre south of the equator the package may round the southern
        # northing up to 10,000 km and write band M with row A, a reference nothing (itself
        # included) decodes; the equator's own reference is a centimetre away.
        text = str(_CONVERTER.toMGRS(0.0, lon, MGRSPrecision=_DIGITS[precision_m]))
    if not spaced:
        return text
    match = _PATTERN.match(text)
    if match is None:  # mgrs only returns UPS references in the areas refused above
        raise MgrsError(f"mgrs returned an unexpected reference {text!r}")
    zone, band, square, digits = match.groups()
    half = len(digits) // 2
    return f"{zone}{band} {square} {digits[:half]} {digits[half:]}"


def from_mgrs(text: str) -> MgrsRef:
    """Decode a 1, 10 or 100 m MGRS reference to its cell centre.

    Spaces and lower case are accepted. Raises ``MgrsError`` naming the input for a
    malformed reference, one of another precision, a polar (UPS) reference, or one whose
    100 km square is not in its latitude band (which the mgrs package decodes, warning).
    """
    compact = re.sub(r"\s+", "", text).upper()
    if _UPS_PATTERN.match(compact):
        raise MgrsError(f"{text!r} is a polar (UPS) reference; only 80° S to 84° N is handled")
    match = _PATTERN.match(compact)
    if match is None or len(match.group(4)) % 2:
        raise MgrsError(f"not an MGRS reference: {text!r}")
    digits = len(match.group(4)) // 2
    if digits not in (3, 4, 5):
        raise MgrsError(f"expected 3 to 5 digits each for easting and northing in {text!r}")
    try:
        with warnings.catch_warnings():
            # The package decodes a square outside its latitude band with a RuntimeWarning
            # ("Latitude Warning") and a point elsewhere: that reference is malformed.
            warnings.simplefilter("error", RuntimeWarning)
            lat, lon = _CONVERTER.toLatLon(compact)
    except RuntimeWarning:
        raise MgrsError(f"{text!r}: the grid square is not in its band") from None
    except (mgrs.core.MGRSError, ValueError) as exc:
        raise MgrsError(f"not a valid MGRS reference: {text!r} ({exc})") from exc
    precision = 10 ** (5 - digits)
    return MgrsRef(float(lat), float(lon), precision, precision * math.sqrt(2) / 2)
