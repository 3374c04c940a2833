"""How the simulated airframe moves when it flies where it is told: a point mass in the air.

``Kinematics`` holds a position, altitude, track and airspeed, and steps them forward in
time under a commanded turn rate (limited by the bank angle a fixed wing may fly,
``max_bank_rad``) and a target altitude (reached at ``climb_mps``). Two steering laws give the
turn rate: ``steer_to`` a point (pure pursuit) and ``steer_orbit`` around a circle (a vector
field that draws the airframe onto the circle and holds it there). No wind, no I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gateway.domain.geodesy import distance_bearing

__all__ = ["FlightState", "Kinematics", "quaternion", "wrap"]

_WGS84_A_M = 6_378_137.0
_WGS84_E2 = 6.694379990141317e-3
_G_MPS2 = 9.80665
#: Heading error (radians) that asks for the full turn rate.
_PURSUIT_GAIN = 2.0


@dataclass(frozen=True, slots=True)
class FlightState:
    """Where the airframe is and how it moves: degrees, metres MSL, radians from north."""

    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    track_rad: float
    speed_mps: float
    turn_rps: float  # positive: turning right
    climb_mps: float
    bank_rad: float


def wrap(angle_rad: float) -> float:
    """``angle_rad`` in [-π, π)."""
    return (angle_rad + math.pi) % math.tau - math.pi


class Kinematics:
    """A fixed wing's position and motion; see the module docstring."""

    def __init__(
        self,
        lat_deg: float,
        lon_deg: float,
        alt_msl_m: float,
        track_rad: float,
        speed_mps: float,
        *,
        max_bank_rad: float = math.radians(35.0),
        climb_mps: float = 4.0,
    ) -> None:
        self.lat_deg, self.lon_deg, self.alt_msl_m = lat_deg, lon_deg, alt_msl_m
        self.track_rad = track_rad % math.tau
        self.speed_mps = speed_mps
        self.max_bank_rad = max_bank_rad
        self.climb_limit_mps = climb_mps
        self.turn_rps = 0.0
        self.climb_mps = 0.0

    @property
    def max_turn_rps(self) -> float:
        """The fastest turn at this speed (a coordinated turn at ``max_bank_rad``)."""
        return _G_MPS2 * math.tan(self.max_bank_rad) / self.speed_mps

    @property
    def min_radius_m(self) -> float:
        """The tightest circle it can fly at this speed."""
        return self.speed_mps / self.max_turn_rps

    def state(self) -> FlightState:
        """The state as telemetry reports it."""
        bank = math.atan(self.speed_mps * self.turn_rps / _G_MPS2)
        return FlightState(
            self.lat_deg, self.lon_deg, self.alt_msl_m, self.track_rad, self.speed_mps,
            self.turn_rps, self.climb_mps, bank,
        )  # fmt: skip

    def to(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """(distance in metres, bearing in radians) from here to a point."""
        distance_m, bearing_deg = distance_bearing(self.lat_deg, self.lon_deg, lat_deg, lon_deg)
        return distance_m, math.radians(bearing_deg)

    def steer_to(self, lat_deg: float, lon_deg: float) -> float:
        """The turn rate that points the airframe at a point."""
        _, bearing = self.to(lat_deg, lon_deg)
        return self._limit(_PURSUIT_GAIN * wrap(bearing - self.track_rad))

    def steer_orbit(
        self, lat_deg: float, lon_deg: float, radius_m: float, *, clockwise: bool
    ) -> float:
        """The turn rate that brings the airframe onto, and holds it on, a circle."""
        distance_m, bearing = self.to(lat_deg, lon_deg)
        side = 1.0 if clockwise else -1.0
        # Tangent to the circle, turned towards the centre by how far outside it we are
        # (away from it inside): straight at the centre from far away.
        lookahead_m = max(radius_m * 0.5, 30.0)
        approach = math.atan((distance_m - radius_m) / lookahead_m)
        wanted = bearing - side * (math.pi / 2 - approach)
        feed_forward = side * self.speed_mps / radius_m if distance_m < 2 * radius_m else 0.0
        return self._limit(feed_forward + _PURSUIT_GAIN * wrap(wanted - self.track_rad))

    def step(self, dt_s: float, turn_rps: float, alt_target_m: float) -> None:
        """Fly ``dt_s`` seconds turning at ``turn_rps`` (limited) towards ``alt_target_m``."""
        self.turn_rps = self._limit(turn_rps)
        climb = max(
            -self.climb_limit_mps, min(self.climb_limit_mps, (alt_target_m - self.alt_msl_m) / dt_s)
        )
        self.climb_mps = climb
        self.alt_msl_m += climb * dt_s
        # The mean track over the step: a turn's arc, not its first tangent.
        mid = self.track_rad + self.turn_rps * dt_s / 2
        distance = self.speed_mps * dt_s
        s2 = math.sin(math.radians(self.lat_deg)) ** 2
        m_lat = _WGS84_A_M * (1 - _WGS84_E2) / (1 - _WGS84_E2 * s2) ** 1.5
        m_lon = _WGS84_A_M / math.sqrt(1 - _WGS84_E2 * s2) * math.cos(math.radians(self.lat_deg))
        self.lat_deg += math.degrees(distance * math.cos(mid) / m_lat)
        self.lon_deg += math.degrees(distance * math.sin(mid) / m_lon)
        if self.lon_deg >= 180.0:
            self.lon_deg -= 360.0
        elif self.lon_deg < -180.0:
            self.lon_deg += 360.0
        self.track_rad = (self.track_rad + self.turn_rps * dt_s) % math.tau

    def _limit(self, turn_rps: float) -> float:
        limit = self.max_turn_rps
        return max(-limit, min(limit, turn_rps))


def quaternion(roll: float, pitch: float, yaw: float) -> list[float]:
    """[w, x, y, z] of Z-Y-X Euler angles (radians), as MAVLink sends attitudes."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]  # fmt: skip
