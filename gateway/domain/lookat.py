"""Where a camera looks: pointing angles between frames, and the optical axis on the ground.

Angles are degrees. Azimuth is clockwise from true north (absolute) or from the nose
(relative to the platform), elevation is above the horizontal (negative looks down).
``absolute_pointing`` and ``relative_pointing`` turn a line of sight between the platform's
body axes and local north-east-down with the platform's roll, pitch and yaw.

``ground_intersection`` finds where the axis first meets the ground: a spherical earth (the
ray's height above a sphere of radius ``EARTH_RADIUS_M`` gains ``h²/2R`` at horizontal distance
h) and the ground elevation looked up along the way (a DEM, or a flat ground given by the
caller). It marches out in steps sized by the clearance left, so a ridge in front of the
flat-earth answer is found, and bisects the crossing. It returns None when the axis misses
the ground (at or above the horizon, grazing past the earth's curve, or beyond range).
Terrain steeper than ``MAX_SLOPE`` can be stepped over by at most ``MIN_STEP_M``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from gateway.domain.geodesy import destination

__all__ = [
    "EARTH_RADIUS_M",
    "GroundPoint",
    "absolute_pointing",
    "flat_intersection",
    "footprint_width_m",
    "ground_intersection",
    "quaternion_to_euler",
    "relative_pointing",
]

#: Mean earth radius: the curvature term only, where metres of error are negligible.
EARTH_RADIUS_M = 6_371_000.0
#: Steepest terrain (rise per metre) the march assumes it cannot step over.
MAX_SLOPE = 1.0
#: Shortest step of the march, in metres of horizontal distance.
MIN_STEP_M = 5.0
_CONVERGED_M = 0.5
_HIGHEST_GROUND_M = 8_900.0
_LOWEST_GROUND_M = -500.0


@dataclass(frozen=True, slots=True)
class GroundPoint:
    """Where the optical axis meets the ground, and how far it is from the sensor."""

    lat_deg: float
    lon_deg: float
    elevation_msl_m: float
    slant_range_m: float
    ground_range_m: float


def quaternion_to_euler(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians (Tait-Bryan Z-Y-X) from a unit quaternion."""
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def _body_to_ned(roll: float, pitch: float, yaw: float) -> tuple[tuple[float, ...], ...]:
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))  # fmt: skip
    return (
        (cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy),
        (cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy),
        (-sp, sr * cp, cr * cp),
    )


def _vector(azimuth_deg: float, elevation_deg: float) -> tuple[float, float, float]:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), -math.sin(el)


def _angles(v: tuple[float, float, float]) -> tuple[float, float]:
    x, y, z = v
    return math.degrees(math.atan2(y, x)) % 360.0, math.degrees(math.atan2(-z, math.hypot(x, y)))


def absolute_pointing(
    roll_rad: float, pitch_rad: float, yaw_rad: float, azimuth_deg: float, elevation_deg: float
) -> tuple[float, float]:
    """(azimuth from north, elevation above the horizon) of a line of sight given in body axes."""
    m = _body_to_ned(roll_rad, pitch_rad, yaw_rad)
    v = _vector(azimuth_deg, elevation_deg)
    ned = (sum(m[0][i] * v[i] for i in range(3)), sum(m[1][i] * v[i] for i in range(3)),
           sum(m[2][i] * v[i] for i in range(3)))  # fmt: skip
    return _angles(ned)


def relative_pointing(
    roll_rad: float, pitch_rad: float, yaw_rad: float, azimuth_deg: float, elevation_deg: float
) -> tuple[float, float]:
    """(azimuth from the nose, elevation above the body's x-y plane) of an absolute sight line."""
    m = _body_to_ned(roll_rad, pitch_rad, yaw_rad)
    v = _vector(azimuth_deg, elevation_deg)
    body = (sum(m[i][0] * v[i] for i in range(3)), sum(m[i][1] * v[i] for i in range(3)),
            sum(m[i][2] * v[i] for i in range(3)))  # fmt: skip
    return _angles(body)


def ground_intersection(
    lat_deg: float,
    lon_deg: float,
    alt_msl_m: float,
    azimuth_deg: float,
    elevation_deg: float,
    ground_msl_m: Callable[[float, float], float | None],
    *,
    fallback_ground_msl_m: float | None = None,
    max_range_m: float = 50_000.0,
) -> GroundPoint | None:
    """Where a line of sight from the sensor first meets the ground; None if it does not.

    ``ground_msl_m(lat, lon)`` gives the ground elevation; where it answers None,
    ``fallback_ground_msl_m`` is the ground (with neither, the answer is None). The ray is
    marched outwards in steps no longer than the terrain could rise to meet it on slopes up
    to ``MAX_SLOPE`` (but at least ``MIN_STEP_M``), and the crossing is bisected to 0.5 m.
    """
    if not elevation_deg < 0 or not all(map(math.isfinite, (lat_deg, lon_deg, alt_msl_m))):
        return None
    tan_d = math.tan(math.radians(-elevation_deg))
    cos_d = math.cos(math.radians(-elevation_deg))
    north, east = _metres_per_degree(lat_deg)
    az = math.radians(azimuth_deg)
    unit_lat, unit_lon = math.cos(az) / north, math.sin(az) / east

    def ground(h: float) -> float | None:
        found = ground_msl_m(lat_deg + h * unit_lat, lon_deg + h * unit_lon)
        return fallback_ground_msl_m if found is None else found

    def above(h: float, g: float) -> float:
        # The ray's height over the ground at horizontal distance h, the earth curving away.
        return alt_msl_m - h * tan_d + h * h / (2 * EARTH_RADIUS_M) - g

    here, g = 0.0, ground(0.0)
    if g is None:
        return None
    clearance = above(0.0, g)
    if clearance <= 0:
        return None  # the sensor is at or below the ground it stands on: no frame centre
    limit = max_range_m * cos_d
    while True:
        step = max(MIN_STEP_M, clearance / (tan_d + MAX_SLOPE))
        ahead = here + step
        if ahead > limit or clearance > _HIGHEST_GROUND_M - _LOWEST_GROUND_M:
            return None  # out of range, or climbing away from any terrain there is
        g_ahead = ground(ahead)
        if g_ahead is None:
            return None
        c_ahead = above(ahead, g_ahead)
        if c_ahead <= 0:
            break
        here, clearance = ahead, c_ahead
    low, high = here, ahead  # the ray is above the ground at low, at or below it at high
    c_low, c_high, g_high = clearance, c_ahead, g_ahead
    while high - low > _CONVERGED_M:
        mid = (low + high) / 2
        g_mid = ground(mid)
        c_mid = -1.0 if g_mid is None else above(mid, g_mid)
        if c_mid <= 0:
            high, c_high, g_high = mid, c_mid, g_mid if g_mid is not None else g_high
        else:
            low, c_low = mid, c_mid
    # Within the last interval the ground is taken as a straight line: interpolate.
    hit = low + (high - low) * c_low / (c_low - c_high) if c_low > c_high else high
    return _point(lat_deg, lon_deg, azimuth_deg, hit, g_high, cos_d)


def _point(
    lat_deg: float, lon_deg: float, azimuth_deg: float, h: float, ground: float, cos_d: float
) -> GroundPoint:
    lat, lon = destination(lat_deg, lon_deg, azimuth_deg, h)
    return GroundPoint(lat, lon, ground, h / cos_d, h)


def flat_intersection(
    lat_deg: float,
    lon_deg: float,
    alt_msl_m: float,
    azimuth_deg: float,
    elevation_deg: float,
    ground_msl_m: float,
    *,
    max_range_m: float = 50_000.0,
) -> GroundPoint | None:
    """``ground_intersection`` over ground at one elevation everywhere: in closed form."""
    if not elevation_deg < 0 or not all(map(math.isfinite, (lat_deg, lon_deg, alt_msl_m))):
        return None
    height = alt_msl_m - ground_msl_m
    tan_d = math.tan(math.radians(-elevation_deg))
    cos_d = math.cos(math.radians(-elevation_deg))
    # height - h·tan + h²/2R = 0: the nearer root, if the ray reaches the sphere at all.
    disc = tan_d * tan_d - 2 * height / EARTH_RADIUS_M
    if height <= 0 or disc < 0:
        return None
    h = 2 * height / (tan_d + math.sqrt(disc))  # the stable form of R(tan - √disc)
    if h > max_range_m * cos_d:
        return None
    return _point(lat_deg, lon_deg, azimuth_deg, h, ground_msl_m, cos_d)


def _metres_per_degree(lat_deg: float) -> tuple[float, float]:
    """Metres per degree of latitude and of longitude at ``lat_deg`` (WGS 84)."""
    s2 = math.sin(math.radians(lat_deg)) ** 2
    a, e2 = 6_378_137.0, 6.694379990141317e-3
    north = math.radians(1) * a * (1 - e2) / (1 - e2 * s2) ** 1.5
    east = math.radians(1) * a / math.sqrt(1 - e2 * s2) * math.cos(math.radians(lat_deg))
    return north, max(east, 1e-6)


def footprint_width_m(slant_range_m: float, hfov_deg: float) -> float:
    """The width a horizontal field of view spans at a slant range, across the line of sight."""
    return 2.0 * slant_range_m * math.tan(math.radians(hfov_deg) / 2.0)
