"""What a ground station on the passthrough may send to an airframe: an allowlist.

The gateway never commands an effector, and what it relays from a ground station is
authenticated by it (sealed in the tunnel or signed with the airframe's key), so the
passthrough decides for every frame, whatever its uplink mode, whether it may go on. The
policy is deny by default: a message or command not listed here is refused.

- Messages in ``RELAYED`` go on; those with a ``target_system`` must name the airframe
  (0, broadcast, only for the read-only requests in ``BROADCAST_OK``).
- COMMAND_LONG and COMMAND_INT go on if their command is in ``COMMANDS``; arming (400,
  MISSION_START 300, which PX4 arms on, and DO_SET_MODE or SET_MODE with the armed flag),
  flight termination (185) and reboot (246) only on a ``signed`` uplink
  (``SIGNED_ONLY_COMMANDS``).
- MISSION_ITEM and MISSION_ITEM_INT go on if their command is in ``MISSION_ITEMS``.
- PARAM_SET and PARAM_EXT_SET go on only for names the passthrough's ``param_set_allow``
  lists, and never for a name that maps outputs (``OUTPUT_PARAMS``).
- FILE_TRANSFER_PROTOCOL goes on only for reading operations (``FTP_READ_OPCODES``).
- What only the gateway says (FISCHER_HOP_SCHEDULE, FISCHER_DETECTION_ACK) never goes on.

Everything else (servo, relay, actuator, gripper, winch, payload place or deploy, parachute,
motor test, actuator targets, RC override, manual control, SETUP_SIGNING, SERIAL_CONTROL,
FTP writes, LOG_ERASE, GPS injection, unknown ids) is refused with a reason that says which
rule refused it. docs/security.md shows this table; a test keeps the two the same.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from fnmatch import fnmatchcase
from typing import Any, Final, Literal

from pymavlink.dialects.v20 import ardupilotmega as m

from gateway.fleet.dialect import MAVLINK_MSG_ID_FISCHER_DETECTION_ACK
from gateway.fleet.hopdialect import MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE

__all__ = [
    "BROADCAST_OK",
    "COMMANDS",
    "COMMAND_MSGS",
    "EFFECTOR_COMMANDS",
    "FTP_READ_OPCODES",
    "GATEWAY_ONLY",
    "MISSION_ITEMS",
    "MISSION_ITEM_MSGS",
    "OUTPUT_PARAMS",
    "RELAYED",
    "SIGNED_ONLY_COMMANDS",
    "Refusal",
    "Uplink",
    "check",
    "may_arm",
]

Uplink = Literal["none", "signed", "open"]

#: Messages only the gateway sends to an airframe.
GATEWAY_ONLY: Final[Mapping[int, str]] = {
    MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE: "FISCHER_HOP_SCHEDULE",
    MAVLINK_MSG_ID_FISCHER_DETECTION_ACK: "FISCHER_DETECTION_ACK",
}


def _ids(*names: str, prefix: str) -> frozenset[int]:
    return frozenset(int(getattr(m, prefix + name)) for name in names)


#: Messages relayed as they are (after the target check).
RELAYED: Final = _ids(
    "HEARTBEAT",
    "SYSTEM_TIME",
    "PING",
    "TIMESYNC",
    "PARAM_REQUEST_READ",
    "PARAM_REQUEST_LIST",
    "PARAM_EXT_REQUEST_READ",
    "PARAM_EXT_REQUEST_LIST",
    "MISSION_REQUEST_LIST",
    "MISSION_REQUEST_PARTIAL_LIST",
    "MISSION_WRITE_PARTIAL_LIST",
    "MISSION_REQUEST",
    "MISSION_REQUEST_INT",
    "MISSION_COUNT",
    "MISSION_ACK",
    "MISSION_CLEAR_ALL",
    "MISSION_SET_CURRENT",
    "COMMAND_ACK",
    "REQUEST_DATA_STREAM",
    "SET_POSITION_TARGET_LOCAL_NED",
    "SET_POSITION_TARGET_GLOBAL_INT",
    "LOG_REQUEST_LIST",
    "LOG_REQUEST_DATA",
    "LOG_REQUEST_END",
    "GIMBAL_MANAGER_SET_ATTITUDE",
    "GIMBAL_MANAGER_SET_PITCHYAW",
    "GIMBAL_MANAGER_SET_MANUAL_CONTROL",
    prefix="MAVLINK_MSG_ID_",
)
#: Read-only requests that may be broadcast (target_system 0).
BROADCAST_OK: Final = _ids(
    "COMMAND_ACK",  # its target is an extension a station may leave out
    "PING",
    "TIMESYNC",
    "PARAM_REQUEST_LIST",
    "MISSION_REQUEST_LIST",
    "REQUEST_DATA_STREAM",
    "LOG_REQUEST_LIST",
    prefix="MAVLINK_MSG_ID_",
)

#: The messages that carry a command, and those that carry a mission item.
COMMAND_MSGS: Final = _ids("COMMAND_LONG", "COMMAND_INT", prefix="MAVLINK_MSG_ID_")
MISSION_ITEM_MSGS: Final = _ids("MISSION_ITEM", "MISSION_ITEM_INT", prefix="MAVLINK_MSG_ID_")
_PARAM_SET_MSGS: Final = _ids("PARAM_SET", "PARAM_EXT_SET", prefix="MAVLINK_MSG_ID_")
_SET_MODE: Final = int(m.MAVLINK_MSG_ID_SET_MODE)
_FTP: Final = int(m.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL)
_ARMED_FLAG: Final = int(m.MAV_MODE_FLAG_SAFETY_ARMED)
#: Mode flags only a signed station may set: armed, hardware in the loop, test.
_SIGNED_MODE_FLAGS: Final = (
    _ARMED_FLAG | int(m.MAV_MODE_FLAG_HIL_ENABLED) | int(m.MAV_MODE_FLAG_TEST_ENABLED)
)
_MISSION_TYPED: Final = _ids(
    "MISSION_COUNT",
    "MISSION_CLEAR_ALL",
    "MISSION_WRITE_PARTIAL_LIST",
    "MISSION_ITEM",
    "MISSION_ITEM_INT",
    prefix="MAVLINK_MSG_ID_",
)
_SAFETY_MISSIONS: Final = frozenset(
    {int(m.MAV_MISSION_TYPE_FENCE), int(m.MAV_MISSION_TYPE_RALLY), int(m.MAV_MISSION_TYPE_ALL)}
)
_REQUEST_DATA_STREAM: Final = int(m.MAVLINK_MSG_ID_REQUEST_DATA_STREAM)
_HOME_COMMANDS: Final = _ids("DO_SET_HOME", prefix="MAV_CMD_")
_SET_MESSAGE_INTERVAL: Final = int(m.MAV_CMD_SET_MESSAGE_INTERVAL)
_DO_SET_MODE: Final = int(m.MAV_CMD_DO_SET_MODE)

#: Flight, mission, camera, gimbal and read-only commands: no effector among them.
COMMANDS: Final = _ids(
    "DO_SET_MODE",
    "NAV_RETURN_TO_LAUNCH",
    "NAV_LAND",
    "NAV_TAKEOFF",
    "NAV_LOITER_UNLIM",
    "DO_SET_MISSION_CURRENT",
    "DO_PAUSE_CONTINUE",
    "DO_CHANGE_SPEED",
    "DO_CHANGE_ALTITUDE",
    "DO_REPOSITION",
    "DO_ORBIT",
    "DO_SET_HOME",
    "DO_SET_ROI_LOCATION",
    "DO_SET_ROI_WPNEXT_OFFSET",
    "DO_SET_ROI_NONE",
    "DO_SET_ROI",
    "DO_MOUNT_CONTROL",
    "DO_MOUNT_CONFIGURE",
    "DO_GIMBAL_MANAGER_PITCHYAW",
    "DO_GIMBAL_MANAGER_CONFIGURE",
    "IMAGE_START_CAPTURE",
    "IMAGE_STOP_CAPTURE",
    "VIDEO_START_CAPTURE",
    "VIDEO_STOP_CAPTURE",
    "SET_CAMERA_MODE",
    "SET_CAMERA_ZOOM",
    "SET_CAMERA_FOCUS",
    "REQUEST_MESSAGE",
    "SET_MESSAGE_INTERVAL",
    "GET_MESSAGE_INTERVAL",
    "REQUEST_AUTOPILOT_CAPABILITIES",
    "REQUEST_PROTOCOL_VERSION",
    "REQUEST_CAMERA_INFORMATION",
    "REQUEST_CAMERA_SETTINGS",
    "REQUEST_STORAGE_INFORMATION",
    "REQUEST_CAMERA_CAPTURE_STATUS",
    "REQUEST_FLIGHT_INFORMATION",
    "REQUEST_VIDEO_STREAM_INFORMATION",
    "REQUEST_VIDEO_STREAM_STATUS",
    "GET_HOME_POSITION",
    prefix="MAV_CMD_",
)
#: Commands relayed only from a ground station that signed them. PX4 arms on MISSION_START
#: ("switch to AUTO_MISSION and ARM" in its commander), so it is arming too.
SIGNED_ONLY_COMMANDS: Final = _ids(
    "COMPONENT_ARM_DISARM",
    "DO_FLIGHTTERMINATION",
    "PREFLIGHT_REBOOT_SHUTDOWN",
    "MISSION_START",
    prefix="MAV_CMD_",
)
#: Commands that move an effector or a payload: named in refusals (refused as any unlisted).
EFFECTOR_COMMANDS: Final = _ids(
    "DO_SET_SERVO",
    "DO_REPEAT_SERVO",
    "DO_SET_RELAY",
    "DO_REPEAT_RELAY",
    "DO_SET_ACTUATOR",
    "DO_GRIPPER",
    "NAV_PAYLOAD_PLACE",
    "DO_WINCH",
    "DO_PARACHUTE",
    "PAYLOAD_PREPARE_DEPLOY",
    "PAYLOAD_CONTROL_DEPLOY",
    "DO_SET_PARAMETER",
    "DO_MOTOR_TEST",
    "DO_SPRAYER",
    "DO_AUX_FUNCTION",
    "DO_SEND_SCRIPT_MESSAGE",
    "DO_ENGINE_CONTROL",
    prefix="MAV_CMD_",
)
#: Mission items: navigation, conditions, camera and gimbal, fence and rally points.
MISSION_ITEMS: Final = _ids(
    "NAV_WAYPOINT",
    "NAV_LOITER_UNLIM",
    "NAV_LOITER_TURNS",
    "NAV_LOITER_TIME",
    "NAV_LOITER_TO_ALT",
    "NAV_RETURN_TO_LAUNCH",
    "NAV_LAND",
    "NAV_TAKEOFF",
    "NAV_DELAY",
    "NAV_VTOL_TAKEOFF",
    "NAV_VTOL_LAND",
    "DO_VTOL_TRANSITION",
    "DO_LAND_START",
    "CONDITION_DELAY",
    "CONDITION_DISTANCE",
    "CONDITION_YAW",
    "DO_JUMP",
    "DO_CHANGE_SPEED",
    "DO_SET_HOME",
    "DO_SET_ROI_LOCATION",
    "DO_SET_ROI_WPNEXT_OFFSET",
    "DO_SET_ROI_NONE",
    "DO_SET_ROI",
    "DO_MOUNT_CONTROL",
    "DO_GIMBAL_MANAGER_PITCHYAW",
    "IMAGE_START_CAPTURE",
    "IMAGE_STOP_CAPTURE",
    "VIDEO_START_CAPTURE",
    "VIDEO_STOP_CAPTURE",
    "DO_SET_CAM_TRIGG_DIST",
    "NAV_FENCE_POLYGON_VERTEX_INCLUSION",
    "NAV_FENCE_POLYGON_VERTEX_EXCLUSION",
    "NAV_FENCE_CIRCLE_INCLUSION",
    "NAV_FENCE_CIRCLE_EXCLUSION",
    "NAV_RALLY_POINT",
    prefix="MAV_CMD_",
)
#: Parameter names that map or drive outputs (PX4 and ArduPilot): never set through here,
#: whatever ``param_set_allow`` says.
OUTPUT_PARAMS: Final = (
    "SERVO*",
    "RELAY*",
    "RC*_OPTION",
    "RC*_FUNCTION",
    "RC_MAP_*",
    "PWM_*",
    "*_FUNC*",
    "CA_*",
    "ACT*",
    "GRIP*",
    "WINCH*",
    "CHUTE*",
    "PLD_*",
    "MNT*_RC*",
    "BTN*",
    "SCR_*",
    "OUT*",
    "DSHOT*",
    "MOT_*",
    "PAYLOAD*",
    "TRIG_*",
    "ICE_*",
    # Arming, termination and the checks that guard them: never from a ground station here.
    "AFS_*",
    "ARMING_*",
    "BRD_SAFETY*",
    "CBRK_*",
    "COM_ARM*",
    "FS_*",
    "SIGNING*",
    "SYSID*",
)
#: MAVLink FTP opcodes that only read (terminate, reset, list, open read-only, read, CRC,
#: burst read).
FTP_READ_OPCODES: Final = frozenset({1, 2, 3, 4, 5, 14, 15})


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why a frame was not relayed: ``reason`` is a metric label, ``detail`` for the log."""

    reason: str
    detail: str


def _command_name(command: int) -> str:
    entry = m.enums["MAV_CMD"].get(command)
    return str(entry.name) if entry is not None else str(command)


def _message_name(msgid: int) -> str:
    cls = m.mavlink_map.get(msgid)
    return str(cls.msgname) if cls is not None else str(msgid)


def may_arm(base_mode: float) -> bool:
    """Whether DO_SET_MODE's ``base_mode`` (param1, a float) may carry the armed flag, or
    the test or hardware-in-the-loop flag (which some autopilots honour).

    An autopilot casts param1 to a uint8_t in C: a value outside 0..255 (1e10), NaN or an
    infinity has no defined cast (an ARM core saturates 1e10 to 0xFF, armed flag set), so
    only a finite value in range whose integer part lacks those flags is taken as harmless.
    """
    if not math.isfinite(base_mode) or not 0 <= base_mode < 256:
        return True
    return bool(int(base_mode) & _SIGNED_MODE_FLAGS)


def _safety_setting(msg: Any, msgid: int) -> str | None:
    """What ``msg`` would change of the airframe's own safety, if anything: its geofence or
    rally points (mission_type 1 or 2), its home (where it returns to), or its telemetry
    (stopping a stream blinds the node). Those need a signed uplink."""
    if msgid in _MISSION_TYPED and int(getattr(msg, "mission_type", 0)) in _SAFETY_MISSIONS:
        return "the geofence or rally points"
    if msgid == _REQUEST_DATA_STREAM and not int(msg.start_stop):
        return "a telemetry stream (stopped)"
    if msgid in COMMAND_MSGS or msgid in MISSION_ITEM_MSGS:
        command = int(msg.command)
        if command in _HOME_COMMANDS:
            return "the home position"
        if command == _SET_MESSAGE_INTERVAL and msgid in COMMAND_MSGS and float(msg.param2) < 0:
            return "a telemetry stream (disabled)"
    return None


def _command(command: int, base_mode: float, uplink: Uplink) -> Refusal | None:
    name = _command_name(command)
    if command in SIGNED_ONLY_COMMANDS or (command == _DO_SET_MODE and may_arm(base_mode)):
        if uplink == "signed":
            return None
        return Refusal(
            "signed_only", f"{name}: arming, termination or reboot needs a signed uplink"
        )
    if command in COMMANDS:
        return None
    if command in EFFECTOR_COMMANDS:
        return Refusal("effector", f"{name} moves an effector or payload: never relayed")
    return Refusal("command_not_allowed", f"{name} is not in the command allowlist")


def _param_name(msg: Any) -> str:
    raw = msg.param_id
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


def check(
    msg: Any, *, sysid: int, uplink: Uplink, param_set_allow: tuple[str, ...] = ()
) -> Refusal | None:
    """None if the parsed pymavlink message ``msg`` may go to the airframe ``sysid``.

    ``uplink`` is the passthrough's mode: with ``none`` nothing goes. The caller has
    already checked the frame's CRC and, on a signed uplink, its signature.
    """
    msgid = int(msg.get_msgId())
    if uplink == "none":
        return Refusal("uplink_none", "this passthrough relays telemetry out only")
    if msgid in GATEWAY_ONLY:
        return Refusal("gateway_only", f"only the gateway sends {GATEWAY_ONLY[msgid]}")
    name = _message_name(msgid)
    target = getattr(msg, "target_system", None)
    if target is not None and target != sysid and not (target == 0 and msgid in BROADCAST_OK):
        return Refusal("wrong_target", f"{name} addressed to system {target}, not {sysid}")
    if uplink != "signed":
        setting = _safety_setting(msg, msgid)
        if setting is not None:
            return Refusal("signed_only", f"{name} changes {setting}: needs a signed uplink")
    if msgid in RELAYED:
        return None
    if msgid in COMMAND_MSGS:
        return _command(int(msg.command), float(msg.param1), uplink)
    if msgid == _SET_MODE:
        if may_arm(float(msg.base_mode)) and uplink != "signed":
            return Refusal(
                "signed_only", "SET_MODE with the armed, test or HIL flag needs a signed uplink"
            )
        return None
    if msgid in MISSION_ITEM_MSGS:
        command = int(msg.command)
        if command in MISSION_ITEMS:
            return None
        reason = "effector" if command in EFFECTOR_COMMANDS else "mission_item_not_allowed"
        return Refusal(reason, f"{name} {_command_name(command)} is not an allowed mission item")
    if msgid in _PARAM_SET_MSGS:
        param = _param_name(msg)
        # ArduPilot finds some parameters whatever their case: the never-list ignores it.
        if any(fnmatchcase(param.upper(), pattern) for pattern in OUTPUT_PARAMS):
            return Refusal("parameter", f"{param} maps outputs: never set through the passthrough")
        if any(fnmatchcase(param, pattern) for pattern in param_set_allow):
            return None
        return Refusal("parameter", f"{param} is not in this passthrough's param_set_allow")
    if msgid == _FTP:
        opcode = msg.payload[3] if len(msg.payload) > 3 else -1
        if opcode in FTP_READ_OPCODES:
            return None
        return Refusal("ftp_write", f"FILE_TRANSFER_PROTOCOL opcode {opcode} writes: refused")
    return Refusal("not_allowed", f"{name} is not in the message allowlist")
