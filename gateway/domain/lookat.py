"""Where a camera looks: pointing angles between frames, and the optical axis on the ground.

Angles are degrees. Azimuth is clockwise from true north (absolute) or from the nose
(relative to the platform), elevation is above the horizontal (negative looks down).
``absolute_pointing`` and ``relative_pointing`` turn a line of sight between the platform's
body axes and local north-east-down with the platform's roll, pitch and yaw.

``ground_intersection`` finds where the axis meets the ground: a spherical earth (the ray's
height above a sphere of radius ``EARTH_RADIUS_M`` gains ``h²/2R`` at horizontal distance h),
and a ground elevation looked up at each estimate (a DEM, or a flat ground given by the
caller), iterated to a fixed point. It returns None when the axis misses the ground (at or
above the horizon, or grazing past the earth's curve). On steep slopes at grazing angles
the iteration may stop before it converges; the last estimate is returned then.
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
    "footprint_width_m",
    "ground_intersection",
    "quaternion_to_euler",
    "relative_pointing",
]

#: Mean earth radius: the curvature term only, where metres of error are negligible.
EARTH_RADIUS_M = 6_371_000.0
_ITERATIONS = 12
_CONVERGED_M = 0.5


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


def _slant_to(height_m: float, depression_rad: float) -> float | None:
    """Slant range at which a ray ``height_m`` above a sphere's surface meets it, or None."""
    if height_m <= 0:
        return 0.0
    sin_d, cos_d = math.sin(depression_rad), math.cos(depression_rad)
    a = cos_d * cos_d / (2 * EARTH_RADIUS_M)
    disc = sin_d * sin_d - 4 * a * height_m
    if disc < 0 or sin_d <= 0:
        return None  # the ray passes over the curve of the earth
    return (sin_d - math.sqrt(disc)) / (2 * a) if a > 0 else height_m / sin_d


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
    """Where a line of sight from the sensor meets the ground; None if it does not (or unknown).

    ``ground_msl_m(lat, lon)`` gives the ground elevation (None where it is not known, when
    ``fallback_ground_msl_m`` is used; with neither, the answer is None).
    """
    if not elevation_deg < 0 or not all(map(math.isfinite, (lat_deg, lon_deg, alt_msl_m))):
        return None
    depression = math.radians(-elevation_deg)
    ground = ground_msl_m(lat_deg, lon_deg)
    ground = fallback_ground_msl_m if ground is None else ground
    if ground is None:
        return None
    slant: float | None = None
    point = (lat_deg, lon_deg)
    for _ in range(_ITERATIONS):
        new = _slant_to(alt_msl_m - ground, depression)
        if new is None or new > max_range_m:
            return None
        horizontal = new * math.cos(depression)
        point = destination(lat_deg, lon_deg, azimuth_deg, horizontal)
        found = ground_msl_m(*point)
        ground = found if found is not None else ground
        if slant is not None and abs(new - slant) < _CONVERGED_M:
            slant = new
            break
        slant = new
    assert slant is not None  # noqa: S101 - the loop ran at least once
    horizontal = slant * math.cos(depression)
    return GroundPoint(point[0], point[1], ground, slant, horizontal)


def footprint_width_m(slant_range_m: float, hfov_deg: float) -> float:
    """The width a horizontal field of view spans at a slant range, across the line of sight."""
    return 2.0 * slant_range_m * math.tan(math.radians(hfov_deg) / 2.0)
