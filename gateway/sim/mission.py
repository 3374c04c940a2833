"""The simulated autopilot's side of MAVLink's mission protocol, as PX4 and ArduPilot answer it.

``MissionServer`` has no I/O and no clock of its own: ``handle(msg, now_s)`` takes one uplink
message (a pymavlink object) at monotonic time ``now_s`` and returns the messages to send
back; ``poll(now_s)`` returns what a step that timed out sends. It keeps the stored mission
and answers:

- an upload: MISSION_COUNT, then MISSION_REQUEST_INT for each item in turn, each step
  re-requested after ``item_timeout_s`` up to ``item_retries`` times and then cancelled
  (MISSION_ACK OPERATION_CANCELLED); MISSION_ITEM_INT (or the older MISSION_ITEM) checked
  as it arrives: an unknown command is UNSUPPORTED, a frame the item cannot use
  UNSUPPORTED_FRAME, a bad parameter or coordinate INVALID_PARAMn (a latitude beyond ±89°
  too: the simulator does not fly over a pole), each ending the upload with the mission
  kept as it was; an item ahead of the one asked for is INVALID_SEQUENCE
  (the upload goes on), one already taken is ignored. More than ``max_items`` is NO_SPACE.
  A second ground station starting an upload while one runs is DENIED. The whole new
  mission replaces the old only with the final MISSION_ACK ACCEPTED; the last item sent
  again (its ACK lost) is acknowledged again.
- a download: MISSION_REQUEST_LIST → MISSION_COUNT; MISSION_REQUEST_INT / MISSION_REQUEST
  per item (INVALID_SEQUENCE out of range).
- MISSION_CLEAR_ALL (ACCEPTED), MISSION_SET_CURRENT (answered by MISSION_CURRENT).

Only the plain mission (``mission_type`` 0) is kept: fences and rally points are
UNSUPPORTED. Nothing here drives an effector: servo, relay, gripper, winch, parachute and
payload items are refused as UNSUPPORTED like any command the airframe does not fly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

from pymavlink.dialects.v20 import ardupilotmega as mav

__all__ = [
    "FLOWN_COMMANDS",
    "MissionHost",
    "MissionServer",
    "SimItem",
    "item_problem",
]

MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_NAV_LOITER_UNLIM = 17
MAV_CMD_NAV_LOITER_TURNS = 18
MAV_CMD_NAV_LOITER_TIME = 19
MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_DO_CHANGE_SPEED = 178
#: The mission items the simulated airframe flies (navigation) or obeys (speed).
FLOWN_COMMANDS = frozenset(
    {
        MAV_CMD_NAV_WAYPOINT,
        MAV_CMD_NAV_LOITER_UNLIM,
        MAV_CMD_NAV_LOITER_TURNS,
        MAV_CMD_NAV_LOITER_TIME,
        MAV_CMD_NAV_RETURN_TO_LAUNCH,
        MAV_CMD_DO_CHANGE_SPEED,
    }
)
_POSITIONED = FLOWN_COMMANDS - {MAV_CMD_NAV_RETURN_TO_LAUNCH, MAV_CMD_DO_CHANGE_SPEED}
#: Frames with a latitude, longitude and altitude (MSL or above home), _INT ones included.
_GLOBAL_FRAMES = frozenset({0, 3, 5, 6})
_MISSION_FRAME = 2
_ALT_RANGE_M = (-500.0, 10_000.0)
_MAX_LAT_DEG = 89.0
_MAX_LOITER_S = 86_400.0
_MAX_RADIUS_M = 10_000.0
_MAX_TURNS = 255.0
_MAX_SPEED_MPS = 100.0


@dataclass(frozen=True, slots=True)
class SimItem:
    """One stored mission item; ``alt_m`` in the item's ``frame`` (MSL or above home)."""

    seq: int
    frame: int
    command: int
    params: tuple[float, float, float, float]
    lat_deg: float
    lon_deg: float
    alt_m: float

    @property
    def is_relative_alt(self) -> bool:
        """True if ``alt_m`` is above home (MAV_FRAME_GLOBAL_RELATIVE_ALT[_INT])."""
        return self.frame in (3, 6)


class MissionHost(Protocol):
    """The autopilot that flies the stored mission."""

    def mission_replaced(self, items: tuple[SimItem, ...]) -> None:
        """A new mission (maybe empty) was accepted whole."""
        ...

    def set_current(self, seq: int) -> bool:
        """Make ``seq`` the current item; False if it is out of range."""
        ...

    def mission_current(self) -> Any:
        """The MISSION_CURRENT message as it stands."""
        ...


def item_problem(
    frame: int, command: int, params: tuple[float, ...], lat_deg: float, lon_deg: float, z: float
) -> int | None:
    """The MAV_MISSION_RESULT refusing this item, or None if the airframe can fly it."""
    if command not in FLOWN_COMMANDS:
        return int(mav.MAV_MISSION_UNSUPPORTED)
    if command == MAV_CMD_DO_CHANGE_SPEED:
        if frame != _MISSION_FRAME and frame not in _GLOBAL_FRAMES:
            return int(mav.MAV_MISSION_UNSUPPORTED_FRAME)
        speed = params[1]
        if not ((math.isfinite(speed) and 0 < speed <= _MAX_SPEED_MPS) or speed == -1):
            return int(mav.MAV_MISSION_INVALID_PARAM2)
        return None
    if frame not in _GLOBAL_FRAMES:
        return int(mav.MAV_MISSION_UNSUPPORTED_FRAME)
    if command == MAV_CMD_NAV_RETURN_TO_LAUNCH:
        return None
    # The simulator flies in a local frame that does not cross a pole (as ``SimProfile``).
    if not (math.isfinite(lat_deg) and -_MAX_LAT_DEG <= lat_deg <= _MAX_LAT_DEG) or (
        lat_deg == 0 and lon_deg == 0
    ):
        return int(mav.MAV_MISSION_INVALID_PARAM5_X)
    if not (math.isfinite(lon_deg) and -180 <= lon_deg <= 180):
        return int(mav.MAV_MISSION_INVALID_PARAM6_Y)
    if not (math.isfinite(z) and _ALT_RANGE_M[0] <= z <= _ALT_RANGE_M[1]):
        return int(mav.MAV_MISSION_INVALID_PARAM7)
    return _param_problem(command, params)


def _param_problem(command: int, params: tuple[float, ...]) -> int | None:
    p1, p2, p3 = params[0], params[1], params[2]
    # NaN is MAVLink's "use the default" for these parameters.
    if command == MAV_CMD_NAV_LOITER_TIME and not (math.isfinite(p1) and 0 <= p1 <= _MAX_LOITER_S):
        return int(mav.MAV_MISSION_INVALID_PARAM1)
    if command == MAV_CMD_NAV_LOITER_TURNS and not (math.isfinite(p1) and 0 < p1 <= _MAX_TURNS):
        return int(mav.MAV_MISSION_INVALID_PARAM1)
    if command == MAV_CMD_NAV_WAYPOINT:
        if not (math.isnan(p1) or 0 <= p1 <= _MAX_LOITER_S):
            return int(mav.MAV_MISSION_INVALID_PARAM1)
        if not (math.isnan(p2) or 0 <= p2 <= _MAX_RADIUS_M):
            return int(mav.MAV_MISSION_INVALID_PARAM2)
    if command in _POSITIONED - {MAV_CMD_NAV_WAYPOINT} and not (
        math.isnan(p3) or abs(p3) <= _MAX_RADIUS_M
    ):
        return int(mav.MAV_MISSION_INVALID_PARAM3)
    return None


@dataclass(slots=True)
class _Upload:
    partner: tuple[int, int]
    count: int
    items: list[SimItem]
    deadline_s: float
    retries_left: int


class MissionServer:
    """The mission store and its protocol (see the module docstring)."""

    def __init__(
        self,
        sysid: int,
        host: MissionHost,
        encoder: Any,
        *,
        max_items: int = 1000,
        item_timeout_s: float = 0.5,
        item_retries: int = 5,
    ) -> None:
        self.sysid = sysid
        self._host = host
        self._mav = encoder
        self.max_items = max_items
        self.item_timeout_s = item_timeout_s
        self.item_retries = item_retries
        self.items: tuple[SimItem, ...] = ()
        self._upload: _Upload | None = None
        #: (partner, count) of the last accepted upload: its last item again is re-acked.
        self._last_accepted: tuple[tuple[int, int], int] | None = None
        #: Uploads accepted, refused (by result name) and messages ignored, for tests and logs.
        self.accepted = 0
        self.refused: dict[str, int] = {}
        self.ignored = 0

    @property
    def is_receiving(self) -> bool:
        """True while an upload is in progress."""
        return self._upload is not None

    def handle(self, msg: Any, now_s: float) -> list[Any]:
        """The answers to one uplink message (empty for one not for us or not ours to answer)."""
        if int(getattr(msg, "target_system", -1)) != self.sysid or int(
            getattr(msg, "target_component", -1)
        ) not in (0, 1):
            return []
        name = msg.get_type()
        partner = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
        mission_type = int(getattr(msg, "mission_type", 0))
        if name == "MISSION_COUNT":
            return self._on_count(partner, int(msg.count), mission_type, now_s)
        if name in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            return self._on_item(partner, msg, mission_type, now_s)
        if name == "MISSION_REQUEST_LIST":
            if mission_type != 0:
                return [self._ack(partner, mav.MAV_MISSION_UNSUPPORTED, mission_type)]
            return [self._mav.mission_count_encode(*partner, len(self.items), 0)]
        if name in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            return self._on_request(partner, int(msg.seq), mission_type, name == "MISSION_REQUEST")
        if name == "MISSION_CLEAR_ALL":
            if mission_type not in (0, mav.MAV_MISSION_TYPE_ALL):
                return [self._ack(partner, mav.MAV_MISSION_UNSUPPORTED, mission_type)]
            self._upload = None
            self._replace(())
            return [self._ack(partner, mav.MAV_MISSION_ACCEPTED, mission_type)]
        if name == "MISSION_SET_CURRENT":
            self._host.set_current(int(msg.seq))
            return [self._host.mission_current()]
        return []

    def poll(self, now_s: float) -> list[Any]:
        """What a timed-out upload step sends: the request again, or the cancelling ACK."""
        upload = self._upload
        if upload is None or now_s < upload.deadline_s:
            return []
        if upload.retries_left <= 0:
            self._upload = None
            return [self._refuse(upload.partner, mav.MAV_MISSION_OPERATION_CANCELLED)]
        upload.retries_left -= 1
        upload.deadline_s = now_s + self.item_timeout_s
        return [self._request(upload)]

    def next_deadline_s(self) -> float:
        """When ``poll`` next has something to do (inf while no upload runs)."""
        return math.inf if self._upload is None else self._upload.deadline_s

    # -- upload -------------------------------------------------------------------------------

    def _on_count(
        self, partner: tuple[int, int], count: int, mission_type: int, now_s: float
    ) -> list[Any]:
        if mission_type != 0:
            return [self._refuse(partner, mav.MAV_MISSION_UNSUPPORTED, mission_type)]
        upload = self._upload
        if upload is not None and upload.partner != partner:
            return [self._refuse(partner, mav.MAV_MISSION_DENIED)]
        if count > self.max_items:
            self._upload = None
            return [self._refuse(partner, mav.MAV_MISSION_NO_SPACE)]
        if count <= 0:
            self._upload = None
            self._replace(())
            self._last_accepted = None
            return [self._ack(partner, mav.MAV_MISSION_ACCEPTED)]
        # The same station counting again starts over, as PX4 and ArduPilot do.
        self._upload = _Upload(partner, count, [], now_s + self.item_timeout_s, self.item_retries)
        return [self._request(self._upload)]

    def _on_item(
        self, partner: tuple[int, int], msg: Any, mission_type: int, now_s: float
    ) -> list[Any]:
        seq = int(msg.seq)
        upload = self._upload
        if upload is None:
            last = self._last_accepted
            if last is not None and last == (partner, seq + 1) and mission_type == 0:
                return [self._ack(partner, mav.MAV_MISSION_ACCEPTED)]  # our ACK was lost
            self.ignored += 1
            return []
        if upload.partner != partner:
            return [self._refuse(partner, mav.MAV_MISSION_DENIED)]
        if mission_type != 0:
            return [self._refuse(partner, mav.MAV_MISSION_UNSUPPORTED, mission_type)]
        expected = len(upload.items)
        if seq < expected:
            self.ignored += 1  # a duplicate: the item asked for comes next
            return []
        if seq > expected:
            return [self._refuse(partner, mav.MAV_MISSION_INVALID_SEQUENCE)]
        item, problem = _item_of(msg)
        if problem is not None:
            self._upload = None
            return [self._refuse(partner, problem)]
        upload.items.append(item)
        if len(upload.items) < upload.count:
            upload.deadline_s = now_s + self.item_timeout_s
            upload.retries_left = self.item_retries
            return [self._request(upload)]
        self._upload = None
        self._replace(tuple(upload.items))
        self._last_accepted = (partner, upload.count)
        self.accepted += 1
        return [self._ack(partner, mav.MAV_MISSION_ACCEPTED), self._host.mission_current()]

    def _replace(self, items: tuple[SimItem, ...]) -> None:
        self.items = items
        self._host.mission_replaced(items)

    def _request(self, upload: _Upload) -> Any:
        return self._mav.mission_request_int_encode(*upload.partner, len(upload.items), 0)

    # -- download -----------------------------------------------------------------------------

    def _on_request(
        self, partner: tuple[int, int], seq: int, mission_type: int, is_float: bool
    ) -> list[Any]:
        if mission_type != 0:
            return [self._ack(partner, mav.MAV_MISSION_UNSUPPORTED, mission_type)]
        if not 0 <= seq < len(self.items):
            return [self._ack(partner, mav.MAV_MISSION_INVALID_SEQUENCE)]
        item = self.items[seq]
        if is_float:
            return [
                self._mav.mission_item_encode(
                    *partner, seq, item.frame, item.command, 0, 1, *item.params,
                    item.lat_deg, item.lon_deg, item.alt_m, 0,
                )
            ]  # fmt: skip
        return [
            self._mav.mission_item_int_encode(
                *partner, seq, item.frame, item.command, 0, 1, *item.params,
                round(item.lat_deg * 1e7), round(item.lon_deg * 1e7), item.alt_m, 0,
            )
        ]  # fmt: skip

    # -- answers ------------------------------------------------------------------------------

    def _ack(self, partner: tuple[int, int], result: int, mission_type: int = 0) -> Any:
        return self._mav.mission_ack_encode(*partner, result, mission_type)

    def _refuse(self, partner: tuple[int, int], result: int, mission_type: int = 0) -> Any:
        name = _RESULT_NAMES.get(int(result), str(result))
        self.refused[name] = self.refused.get(name, 0) + 1
        return self._ack(partner, result, mission_type)


_RESULT_NAMES = {int(k): str(v.name) for k, v in mav.enums["MAV_MISSION_RESULT"].items()}


def _item_of(msg: Any) -> tuple[SimItem, int | None]:
    """The item a MISSION_ITEM_INT or MISSION_ITEM carries, and what is wrong with it."""
    frame, command = int(msg.frame), int(msg.command)
    params = (float(msg.param1), float(msg.param2), float(msg.param3), float(msg.param4))
    if msg.get_type() == "MISSION_ITEM_INT":
        lat_deg, lon_deg = int(msg.x) / 1e7, int(msg.y) / 1e7
    else:
        lat_deg, lon_deg = float(msg.x), float(msg.y)
    z = float(msg.z)
    item = SimItem(int(msg.seq), frame, command, params, lat_deg, lon_deg, z)
    return item, item_problem(frame, command, params, lat_deg, lon_deg, z)
