"""What an order asks of an airframe, and whether the airframe can do it: pure, no I/O.

``plan`` turns a ``FiveLineOrder`` and the airframe's latest ``Telemetry`` into a ``Plan``:
the mission steps to upload (none for return to base; a lawnmower over an area, sized by
the sensor's footprint at the height above ground, ``processors._coverage``), the points the
airframe will fly through (from where it is, over the task, back home) and the time it will
spend on task. An area whose survey cannot be planned is refused (``area``).
``check`` runs the acceptance checks on a plan, in order, and returns the first that fails
as a ``Refusal`` naming the check and its numbers:

- ``geofence``: every point of the route, and every leg flown as the geodesic and as the
  rhumb line (``gateway.domain.paths``), inside the airframe's fence, whose edges are
  geodesics (``gateway.domain.mission.route_exit``); a refusal says how far outside;
- ``terrain``: at every task point and along the inbound and task legs (their geodesic and,
  where it parts from it, their rhumb line), where a DEM covers them, the commanded
  altitude is at least the ground plus the clearance plus 3σ of height above ground
  (``gateway.domain.terrain.safe_floor_agl_m``, σ from the barometer and the DEM);
- ``endurance``: the route at cruise speed, the time on task and the reserve fit in the
  predicted endurance the telemetry carries (``gateway.domain.energy``).

Airframe, link and time-window checks need the commander and the clock, so the processor
makes them before planning.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise

from gateway.domain.geodesy import destination
from gateway.domain.mission import (
    Excursion,
    Loiter,
    MissionStep,
    Waypoint,
    polygon_problem,
    route_exit,
    route_length_m,
)
from gateway.domain.paths import geodesic_points, linear_bow_m, rhumb_bow_m, rhumb_points
from gateway.domain.terrain import SAFETY_SIGMAS, TerrainModel, agl_sigma, safe_floor_agl_m
from gateway.events import FiveLineOrder, OrderTask, Telemetry
from processors._coverage import lawnmower

__all__ = ["Limits", "Plan", "Refusal", "check", "plan"]

LatLon = tuple[float, float]

#: Spacing of the terrain check's samples along the route, and their most in all.
_SAMPLE_SPACING_M = 250.0
_MAX_SAMPLES = 5000
_M_PER_DEG = 111_320.0
#: A leg whose geodesic, rhumb line and latitude-longitude line are all within this of each
#: other is sampled along the last (the cheapest); see ``_samples``.
_TERRAIN_TOLERANCE_M = 5.0
#: The loiter circle is checked as the octagon round it (corners at radius / cos 22.5°),
#: which holds the whole circle: at most 8 % of the radius further out than the circle.
_OCTAGON = 8


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why an order is not accepted: the ``check`` that failed and a ``reason`` with numbers."""

    check: str
    reason: str


@dataclass(frozen=True, slots=True)
class Limits:
    """The processor's options the checks need."""

    cruise_speed_mps: float
    reserve_min: float
    time_on_task_s: float
    loiter_radius_m: float
    clearance_m: float
    baro_sigma_m: float
    fence: tuple[LatLon, ...] | None
    camera_hfov_deg: float = 60.0
    survey_overlap: float = 0.2
    max_survey_lines: int = 100


@dataclass(frozen=True, slots=True)
class Plan:
    """What the airframe will do for an order (see the module docstring)."""

    items: tuple[MissionStep, ...]
    task_points: tuple[LatLon, ...]
    route: tuple[LatLon, ...]
    alt_msl_m: float
    on_task_s: float
    route_m: float
    """The route's geodesic length (m), worked out once."""
    swath_m: float | None = None
    """For a survey: the sensor's swath width on the ground (m) the lines are spaced by."""

    @property
    def is_return(self) -> bool:
        """True for return to base: a command, no mission."""
        return not self.items


def _fmt(point: LatLon) -> str:
    return f"{point[0]:.5f}, {point[1]:.5f}"


def plan(
    order: FiveLineOrder,
    telemetry: Telemetry,
    home: LatLon | None,
    limits: Limits,
    terrain: TerrainModel | None = None,
) -> Plan | Refusal:
    """The plan for ``order`` on the airframe of ``telemetry`` (which must have a position);
    ``terrain`` gives a survey's height above ground (``processors._coverage``)."""
    here = telemetry.position
    if here is None:
        return Refusal("link", f"{telemetry.airframe} has reported no position")
    start: LatLon = (here.lat_deg, here.lon_deg)
    back = home or start
    if order.task is OrderTask.RETURN_TO_BASE:
        home_leg: tuple[LatLon, ...] = (start, back)
        return Plan((), (), home_leg, here.alt_msl_m or 0.0, 0.0, route_length_m(home_leg))
    area = order.location
    given = area.point.alt_msl_m if area.point is not None else area.polygon[0].alt_msl_m
    alt = given if given is not None else here.alt_msl_m
    if alt is None:
        return Refusal("terrain", "no altitude to command: the order gives none, nor the airframe")
    if area.point is not None:
        point = (area.point.lat_deg, area.point.lon_deg)
        radius = limits.loiter_radius_m
        items: tuple[MissionStep, ...] = (
            Waypoint(point[0], point[1], alt),
            Loiter(point[0], point[1], alt, limits.time_on_task_s, radius),
        )
        # The loiter circle: its far side is still flown, so check it for fence and terrain,
        # as the octagon drawn round it (its legs never cut inside the circle).
        out_r = radius / math.cos(math.pi / _OCTAGON)
        circle = tuple(
            destination(point[0], point[1], 360.0 * i / _OCTAGON, out_r) for i in range(_OCTAGON)
        )
        task: tuple[LatLon, ...] = (point, *circle, point)
        orbit_m = 2 * math.pi * radius
        on_task_s = max(limits.time_on_task_s, orbit_m / limits.cruise_speed_mps)
        route = (start, point, back)
        return Plan(items, task, route, alt, on_task_s, route_length_m(route))
    corners = tuple((p.lat_deg, p.lon_deg) for p in area.polygon)
    problem = polygon_problem(corners)
    if problem is not None:
        return Refusal("area", f"the order's polygon {problem}")
    return _survey(corners, alt, telemetry, back, terrain, limits)


def _ground_m(
    corners: tuple[LatLon, ...], telemetry: Telemetry, terrain: TerrainModel | None
) -> float | None:
    """The highest ground found on the area's edge and at its centre, from the DEM; else the
    ground under the airframe (its MSL less its AGL altitude); else its home's (its MSL less
    its altitude above home); None when none is known."""
    if terrain is not None:
        centre = (
            sum(c[0] for c in corners) / len(corners),
            sum(c[1] for c in corners) / len(corners),
        )
        found = [
            terrain.lookup(lat, lon) for lat, lon in (*_samples((*corners, corners[0])), centre)
        ]
        heights = [f[0] for f in found if f is not None]
        if heights:
            return max(heights)
    here = telemetry.position
    if here is None or here.alt_msl_m is None:
        return None
    if telemetry.alt_agl_m is not None:
        return here.alt_msl_m - telemetry.alt_agl_m
    if here.alt_rel_home_m is not None:
        return here.alt_msl_m - here.alt_rel_home_m
    return None


def _survey(
    corners: tuple[LatLon, ...],
    alt: float,
    telemetry: Telemetry,
    back: LatLon,
    terrain: TerrainModel | None,
    limits: Limits,
) -> Plan | Refusal:
    """A lawnmower over the area, sized by the sensor's footprint at the planned height."""
    ground = _ground_m(corners, telemetry, terrain)
    if ground is None:
        return Refusal(
            "area",
            "no height above ground to size the sensor footprint: no DEM covers the area and"
            f" {telemetry.airframe} reports no height above ground nor above home",
        )
    height = alt - ground
    if height <= 0:
        return Refusal(
            "terrain", f"commanded {alt:.1f} m MSL is not above the area's ground {ground:.1f} m"
        )
    survey = lawnmower(
        corners,
        height_agl_m=height,
        hfov_deg=limits.camera_hfov_deg,
        overlap=limits.survey_overlap,
        max_lines=limits.max_survey_lines,
    )
    if isinstance(survey, str):
        return Refusal("area", survey)
    start = (telemetry.position.lat_deg, telemetry.position.lon_deg) if telemetry.position else back
    points = survey.points
    items = tuple(Waypoint(lat, lon, alt) for lat, lon in points)
    pattern_m = route_length_m(points) if len(points) > 1 else 0.0
    legs_m = route_length_m((start, points[0])) + route_length_m((points[-1], back))
    return Plan(
        items,
        points,
        (start, *points, back),
        alt,
        pattern_m / limits.cruise_speed_mps,
        pattern_m + legs_m,
        survey.swath_m,
    )


def _samples(points: Sequence[LatLon]) -> list[LatLon]:
    """The points and, between them, a sample every ``_SAMPLE_SPACING_M`` for the terrain
    check (sparser on a very long route: ``_MAX_SAMPLES`` per path in all at most).

    A leg is sampled along the paths an autopilot flies (``gateway.domain.paths``): its
    geodesic and, where that parts from it by more than ``_TERRAIN_TOLERANCE_M``, its rhumb
    line too. A short leg, where the two and the line linear in latitude and longitude are
    all within ``_TERRAIN_TOLERANCE_M`` of each other, is sampled along the last, which costs
    a tenth as much (the legs of an area order are short: its 64 corners are checked in
    milliseconds, on the event loop); those samples are within 10 m of either path.
    """
    legs = []
    for a, b in pairwise(points):
        dlat = b[0] - a[0]
        dlon = (b[1] - a[1] + 180.0) % 360.0 - 180.0
        east_m = dlon * _M_PER_DEG * math.cos(math.radians((a[0] + b[0]) / 2))
        legs.append((a, b, dlat, dlon, math.hypot(dlat * _M_PER_DEG, east_m)))
    total_m = sum(leg[4] for leg in legs)
    spacing_m = max(_SAMPLE_SPACING_M, total_m / _MAX_SAMPLES)
    out: list[LatLon] = list(points[:1])
    for a, b, dlat, dlon, length_m in legs:
        steps = math.ceil(length_m / spacing_m)
        bow_m = rhumb_bow_m(a, b, length_m)
        if bow_m > _TERRAIN_TOLERANCE_M or linear_bow_m(a, b) > _TERRAIN_TOLERANCE_M:
            out.extend(geodesic_points(a, b, spacing_m)[1:])
            if bow_m > _TERRAIN_TOLERANCE_M:
                out.extend(rhumb_points(a, b, steps)[1:-1])
            continue
        for i in range(1, steps):
            f = i / steps
            out.append((a[0] + f * dlat, (a[1] + f * dlon + 180.0) % 360.0 - 180.0))
        out.append(b)
    return out


def _distance(metres: float) -> str:
    return f"{metres:.0f} m" if metres < 10_000 else f"{metres / 1000:.1f} km"


def _fence_reason(where: Excursion) -> str:
    reason = (
        f"the route leaves the geofence at {_fmt(where.point)} (lat, lon),"
        f" {_distance(where.outside_m)} outside"
    )
    if where.leg is not None:
        a, b = where.leg
        reason += f", on the leg {_fmt(a)} to {_fmt(b)} flown as the {where.path}"
    return reason


def check(
    plan: Plan, telemetry: Telemetry, terrain: TerrainModel | None, limits: Limits
) -> Refusal | None:
    """The first acceptance check ``plan`` fails (see the module docstring), or None."""
    fence = limits.fence
    if fence is not None:
        points = (
            plan.route if plan.is_return else (*plan.route[:1], *plan.task_points, plan.route[-1])
        )
        outside = route_exit(fence, points)
        if outside is not None:
            return Refusal("geofence", _fence_reason(outside))
    if terrain is not None and not plan.is_return:
        worst: tuple[float, float, float, float, LatLon] | None = None
        # The inbound leg is flown towards the commanded altitude too; the way home is the
        # autopilot's own return (its RTL altitude), not ours to check.
        for point in _samples((plan.route[0], *plan.task_points)):
            found = terrain.lookup(point[0], point[1])
            if found is None:
                continue
            ground, source = found
            sigma = agl_sigma(limits.baro_sigma_m, source.sigma_m)
            floor = ground + safe_floor_agl_m(sigma, limits.clearance_m)
            if plan.alt_msl_m < floor and (worst is None or floor > worst[0]):
                worst = (floor, ground, sigma, plan.alt_msl_m, point)
        if worst is not None:
            floor, ground, sigma, alt, point = worst
            return Refusal(
                "terrain",
                f"commanded {alt:.1f} m MSL is below the floor {floor:.1f} m MSL at {_fmt(point)}"
                f" (ground {ground:.1f} m + clearance {limits.clearance_m:.1f} m"
                f" + {SAFETY_SIGMAS:g}σ, σ {sigma:.1f} m)",
            )
    have_min = telemetry.endurance_remaining_min
    if have_min is None:
        return Refusal("endurance", f"{telemetry.airframe} reports no battery state")
    route_m = plan.route_m
    fly_min = route_m / limits.cruise_speed_mps / 60.0
    task_min = plan.on_task_s / 60.0
    need_min = fly_min + task_min + limits.reserve_min
    if need_min > have_min:
        return Refusal(
            "endurance",
            f"needs {need_min:.1f} min ({route_m / 1000:.1f} km at"
            f" {limits.cruise_speed_mps:g} m/s {fly_min:.1f} min + on task {task_min:.1f} min"
            f" + reserve {limits.reserve_min:g} min), has {have_min:.1f} min",
        )
    return None
