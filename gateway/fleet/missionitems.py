"""Mission steps and tasking intents as MAVLink: mission items, commands, autopilot modes.

The orders processor speaks in intents (upload these steps, start the mission, return to
base) and domain steps (``gateway.domain.mission``); this is where they become MAVLink. A
``Waypoint`` is MAV_CMD_NAV_WAYPOINT, a ``Loiter`` MAV_CMD_NAV_LOITER_TIME (time, radius),
both in MAV_FRAME_GLOBAL (altitude MSL). Starting a mission and returning home depend on the
autopilot (``Autopilot``): with ``px4``, MAV_CMD_DO_SET_MODE with PX4's AUTO.MISSION or
AUTO.RTL custom mode (what PX4 and MAVSDK's autopilot server take); with ``ardupilot``,
MAV_CMD_DO_SET_MODE with ArduPilot's mode number, AUTO or RTL (ArduPlane 10 and 11, ArduCopter
3 and 6, by ``Vehicle``); with ``mavlink``, MAV_CMD_MISSION_START (first to last item) or
MAV_CMD_NAV_RETURN_TO_LAUNCH.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from gateway.domain.mission import Loiter, MissionStep

__all__ = [
    "ARDUCOPTER_AUTO",
    "ARDUCOPTER_RTL",
    "ARDUPLANE_AUTO",
    "ARDUPLANE_RTL",
    "MAV_CMD_DO_SET_MODE",
    "MAV_CMD_MISSION_START",
    "MAV_CMD_NAV_LOITER_TIME",
    "MAV_CMD_NAV_RETURN_TO_LAUNCH",
    "MAV_CMD_NAV_WAYPOINT",
    "Autopilot",
    "MissionItem",
    "Vehicle",
    "mission_item",
    "return_command",
    "start_command",
]

MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_NAV_LOITER_TIME = 19
MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_MISSION_START = 300
#: MAV_FRAME_GLOBAL: latitude, longitude, altitude above mean sea level.
MAV_FRAME_GLOBAL = 0
#: DO_SET_MODE parameters for PX4: custom mode enabled, main mode AUTO, sub mode.
PX4_AUTO_MISSION = (1.0, 4.0, 4.0)
PX4_AUTO_RTL = (1.0, 4.0, 5.0)
#: ArduPilot's mode numbers (HEARTBEAT.custom_mode, DO_SET_MODE param 2) for AUTO and RTL.
ARDUPLANE_AUTO, ARDUPLANE_RTL = 10, 11
ARDUCOPTER_AUTO, ARDUCOPTER_RTL = 3, 6
#: DO_SET_MODE's base mode: MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, nothing else (never armed).
_CUSTOM_MODE = 1.0

Autopilot = Literal["px4", "ardupilot", "mavlink"]
"""Whose modes start a mission and send an airframe home: PX4's, ArduPilot's, or none (the
plain MAVLink commands)."""

Vehicle = Literal["plane", "copter"]
"""Which of ArduPilot's mode tables applies: ArduPlane's (fixed wing, VTOL) or ArduCopter's."""


@dataclass(frozen=True, slots=True)
class MissionItem:
    """One MAVLink mission item: a navigation ``command`` at a point, altitude metres MSL."""

    command: int
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    frame: int = MAV_FRAME_GLOBAL


def mission_item(step: MissionStep) -> MissionItem:
    """The MAVLink mission item of one mission step."""
    if isinstance(step, Loiter):
        return MissionItem(
            MAV_CMD_NAV_LOITER_TIME,
            step.lat_deg,
            step.lon_deg,
            step.alt_msl_m,
            (step.seconds, 0.0, step.radius_m, 0.0),
        )
    return MissionItem(MAV_CMD_NAV_WAYPOINT, step.lat_deg, step.lon_deg, step.alt_msl_m)


def start_command(
    autopilot: Autopilot, items: int, vehicle: Vehicle = "plane"
) -> tuple[int, tuple[float, ...]]:
    """The command (and its parameters) that starts a mission of ``items`` items."""
    if autopilot == "px4":
        return MAV_CMD_DO_SET_MODE, PX4_AUTO_MISSION
    if autopilot == "ardupilot":
        mode = ARDUPLANE_AUTO if vehicle == "plane" else ARDUCOPTER_AUTO
        return MAV_CMD_DO_SET_MODE, (_CUSTOM_MODE, float(mode), 0.0)
    return MAV_CMD_MISSION_START, (0.0, float(items - 1))


def return_command(
    autopilot: Autopilot, vehicle: Vehicle = "plane"
) -> tuple[int, tuple[float, ...]]:
    """The command (and its parameters) that sends an airframe home."""
    if autopilot == "px4":
        return MAV_CMD_DO_SET_MODE, PX4_AUTO_RTL
    if autopilot == "ardupilot":
        mode = ARDUPLANE_RTL if vehicle == "plane" else ARDUCOPTER_RTL
        return MAV_CMD_DO_SET_MODE, (_CUSTOM_MODE, float(mode), 0.0)
    return MAV_CMD_NAV_RETURN_TO_LAUNCH, ()
