"""Mission steps and tasking intents as MAVLink: mission items, commands, autopilot modes.

The orders processor speaks in intents (upload these steps, start the mission, return to
base) and domain steps (``gateway.domain.mission``); this is where they become MAVLink. A
``Waypoint`` is MAV_CMD_NAV_WAYPOINT, a ``Loiter`` MAV_CMD_NAV_LOITER_TIME (time, radius),
both in MAV_FRAME_GLOBAL (altitude MSL). Starting a mission and returning home depend on the
autopilot (``ModeCommands``): with ``px4``, MAV_CMD_DO_SET_MODE with PX4's AUTO.MISSION or
AUTO.RTL custom mode (what PX4 and MAVSDK's autopilot server take); with ``mavlink``,
MAV_CMD_MISSION_START (first to last item) or MAV_CMD_NAV_RETURN_TO_LAUNCH.
"""

from __future__ import annotations

from dataclasses import dataclass

from gateway.domain.mission import Loiter, MissionStep, ModeCommands

__all__ = [
    "MAV_CMD_DO_SET_MODE",
    "MAV_CMD_MISSION_START",
    "MAV_CMD_NAV_LOITER_TIME",
    "MAV_CMD_NAV_RETURN_TO_LAUNCH",
    "MAV_CMD_NAV_WAYPOINT",
    "MissionItem",
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


def start_command(mode_commands: ModeCommands, items: int) -> tuple[int, tuple[float, ...]]:
    """The command (and its parameters) that starts a mission of ``items`` items."""
    if mode_commands == "px4":
        return MAV_CMD_DO_SET_MODE, PX4_AUTO_MISSION
    return MAV_CMD_MISSION_START, (0.0, float(items - 1))


def return_command(mode_commands: ModeCommands) -> tuple[int, tuple[float, ...]]:
    """The command (and its parameters) that sends an airframe home."""
    if mode_commands == "px4":
        return MAV_CMD_DO_SET_MODE, PX4_AUTO_RTL
    return MAV_CMD_NAV_RETURN_TO_LAUNCH, ()
