"""The paths an autopilot flies between two waypoints: the geodesic and the rhumb line.

Neither autopilot flies "the straight line" between two waypoints on the ellipsoid; each
follows a straight line in a flat frame of its own (read in their sources: PX4 1.14–1.15
``src/modules/fw_pos_control/FixedwingPositionControl.cpp`` with ``src/lib/geo/geo.cpp``,
ArduPilot 4.x ``libraries/AP_L1_Control/AP_L1_Control.cpp`` with
``libraries/AP_Common/Location.cpp``):

- **PX4** (fixed wing, NPFG guidance; the rover the same) projects the previous and current
  waypoint and its own position into an azimuthal equidistant plane on a 6371 km sphere,
  centred on the EKF's local origin (``MapProjection::project``), and follows the straight
  line between the two waypoints there. That line is close to the **geodesic**: for
  the legs of up to 200 km at 65° N we measured, with the origin up to 200 km away, within
  13 m of it (within 2 m with the origin on the leg).
- **ArduPilot** (plane, L1 guidance) measures its cross-track error in a north-east frame
  at the previous waypoint whose east axis is scaled by the cosine of the mean latitude
  (``Location::get_distance_NE``): it flies where Δlat : Δlon·cos(mean lat) is the leg's
  own ratio, which is close to the **rhumb line** (constant bearing): within 22 m of it
  for the legs of up to 200 km at 60–66° N we measured; an east–west leg is flown exactly
  along its parallel.

The two part by ``rhumb_bow_m``: 1.2 km in the middle of a 170 km east–west leg at 65° N.
Being conservative means checking both: the geofence and the terrain floor are checked
along each (``processors._orderplan``). Neither check adds a margin for how well the
airframe holds its line (wind, turns); a fence should leave one.

The rhumb line is worked out on the ellipsoid (isometric latitude ψ and longitude are linear
along it), the geodesic by geographiclib.
"""

from __future__ import annotations

import math

from geographiclib.geodesic import Geodesic  # type: ignore[import-untyped]

__all__ = ["geodesic_points", "linear_bow_m", "rhumb_at", "rhumb_bow_m", "rhumb_points"]

LatLon = tuple[float, float]

_GEOD = Geodesic.WGS84
_A = float(_GEOD.a)
_E2 = float(_GEOD.f) * (2 - float(_GEOD.f))
_E = math.sqrt(_E2)
#: Latitudes are clamped this far from a pole, where rhumb lines spiral without end.
_MAX_LAT = 89.5
_LATLON = Geodesic.LATITUDE | Geodesic.LONGITUDE


def _wrap(dlon: float) -> float:
    return (dlon + 180.0) % 360.0 - 180.0


def _psi(lat: float) -> float:
    """Isometric latitude (rad) of a geodetic latitude (degrees)."""
    phi = math.radians(max(-_MAX_LAT, min(_MAX_LAT, lat)))
    return math.asinh(math.tan(phi)) - _E * math.atanh(_E * math.sin(phi))


def _lat(psi: float) -> float:
    """Geodetic latitude (degrees) of an isometric latitude: a fixed point in e², 5 steps
    take it below 1e-12 rad."""
    phi = math.atan(math.sinh(psi))
    for _ in range(5):
        phi = math.atan(math.sinh(psi + _E * math.atanh(_E * math.sin(phi))))
    return math.degrees(phi)


def rhumb_bow_m(a: LatLon, b: LatLon, length_m: float) -> float:
    """About how far apart (m) the rhumb line and the geodesic from ``a`` to ``b`` are, at
    most: a rhumb line at bearing α bends away from the geodesic with curvature
    |sin α|·tan φ / N, so over a leg of length L they part by up to that times L²/8 (taken
    at the leg's highest |latitude|, and 1 % added, so an upper estimate)."""
    dpsi = _psi(b[0]) - _psi(a[0])
    dlam = math.radians(_wrap(b[1] - a[1]))
    hyp = math.hypot(dpsi, dlam)
    if hyp == 0.0:
        return 0.0
    phi = math.radians(min(_MAX_LAT, max(abs(a[0]), abs(b[0]))))
    prime_vertical = _A / math.sqrt(1 - _E2 * math.sin(phi) ** 2)
    curvature = abs(dlam) / hyp * math.tan(phi) / prime_vertical
    return 1.01 * curvature * length_m * length_m / 8.0


def linear_bow_m(a: LatLon, b: LatLon) -> float:
    """About how far (m) the line linear in latitude and longitude departs from the rhumb
    line: ψ is not linear in latitude, the two part by tan φ·Δφ²/8 of a radian of latitude."""
    phi = math.radians(min(_MAX_LAT, max(abs(a[0]), abs(b[0]))))
    dphi = math.radians(b[0] - a[0])
    return math.tan(phi) * dphi * dphi / 8.0 * _A


def geodesic_points(a: LatLon, b: LatLon, spacing_m: float) -> list[LatLon]:
    """Points along the geodesic from ``a`` to ``b``, ``a`` and ``b`` included, at most
    ``spacing_m`` apart."""
    line = _GEOD.InverseLine(a[0], a[1], b[0], b[1], _LATLON | Geodesic.DISTANCE)
    steps = max(1, math.ceil(float(line.s13) / spacing_m))
    out = [a]
    for i in range(1, steps):
        got = line.Position(line.s13 * i / steps, _LATLON)
        out.append((float(got["lat2"]), float(got["lon2"])))
    out.append(b)
    return out


def rhumb_at(a: LatLon, b: LatLon, f: float) -> LatLon:
    """The point a fraction ``f`` of the way along the rhumb line from ``a`` to ``b``, in
    isometric latitude and longitude (so, to within the ratio of cos φ at the ends, of the
    way in distance)."""
    psi_a = _psi(a[0])
    return _lat(psi_a + f * (_psi(b[0]) - psi_a)), _wrap(a[1] + f * _wrap(b[1] - a[1]))


def rhumb_points(a: LatLon, b: LatLon, pieces: int) -> list[LatLon]:
    """``pieces`` + 1 points along the rhumb line from ``a`` to ``b``, ends included (see
    ``rhumb_at``)."""
    psi_a, psi_b = _psi(a[0]), _psi(b[0])
    dlon = _wrap(b[1] - a[1])
    out = [a]
    for i in range(1, pieces):
        f = i / pieces
        out.append((_lat(psi_a + f * (psi_b - psi_a)), _wrap(a[1] + f * dlon)))
    out.append(b)
    return out
