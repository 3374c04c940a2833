"""The fleet commander sends only reconnaissance: never arm, release, servo or parameter."""

from __future__ import annotations

import anyio
import pytest

from gateway.fleet.commander import FleetCommander
from gateway.fleet.missionitems import MAV_CMD_NAV_WAYPOINT, MissionItem

MAV_CMD_DO_SET_SERVO = 183
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_DO_SET_ACTUATOR = 187
MAV_CMD_DO_GRIPPER = 211
MAV_CMD_DO_SET_PARAMETER = 180
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_DO_PARACHUTE = 208


def commander() -> FleetCommander:
    # No sessions at all: a refused command must be refused before any session is looked up.
    return FleetCommander({}, lambda _airframe: True)


@pytest.mark.parametrize(
    ("command", "params"),
    [
        (MAV_CMD_COMPONENT_ARM_DISARM, (1.0,)),
        (MAV_CMD_DO_SET_SERVO, (9.0, 2000.0)),
        (MAV_CMD_DO_SET_ACTUATOR, (1.0,)),
        (MAV_CMD_DO_GRIPPER, (1.0, 0.0)),
        (MAV_CMD_DO_SET_PARAMETER, (1.0, 1.0)),
        (MAV_CMD_DO_PARACHUTE, (2.0,)),
        (MAV_CMD_DO_SET_MODE, (129.0, 4.0, 4.0)),  # base mode with SAFETY_ARMED
        (MAV_CMD_DO_SET_MODE, ()),
    ],
)
def test_commands_that_are_not_reconnaissance_are_refused(
    command: int, params: tuple[float, ...]
) -> None:
    outcome = anyio.run(
        lambda: commander().command("F26E-001", command, params, timeout_s=1.0, retries=0)
    )
    assert not outcome.ok
    assert outcome.attempts == 0
    assert "not a reconnaissance command" in outcome.detail


@pytest.mark.parametrize(
    "command", [MAV_CMD_DO_SET_SERVO, MAV_CMD_DO_GRIPPER, MAV_CMD_COMPONENT_ARM_DISARM, 205]
)
def test_mission_items_that_are_not_navigation_are_refused(command: int) -> None:
    items = (
        MissionItem(MAV_CMD_NAV_WAYPOINT, 65.0, 21.0, 500.0),
        MissionItem(command, 65.0, 21.0, 500.0),
    )
    outcome = anyio.run(
        lambda: commander().upload_items("F26E-001", items, timeout_s=1.0, retries=0)
    )
    assert not outcome.ok
    assert outcome.attempts == 0
    assert f"[{command}]" in outcome.detail
