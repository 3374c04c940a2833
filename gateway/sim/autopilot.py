"""The simulated airframe's autopilot: its modes as PX4 or ArduPilot names them, and its mission.

``Autopilot`` starts on the airframe's deterministic orbit (``SimulatedAirframe``'s circle,
reported as PX4's AUTO.LOITER, ArduPlane's or ArduCopter's GUIDED) and takes over the flying
itself, with ``Kinematics``, from the first mode it is told to fly: ``hold`` (circle where it
is: PX4 AUTO.LOITER; ArduPlane LOITER, GUIDED or CIRCLE; ArduCopter LOITER, GUIDED, CIRCLE or
POSHOLD), ``mission`` (fly the stored items: PX4 AUTO.MISSION, ArduPilot AUTO) or ``rtl``
(home, then circle it: PX4 AUTO.RTL, ArduPilot RTL). ArduCopter is flown with the same
kinematics: it circles where a copter would hover. Modes come from MAV_CMD_DO_SET_MODE
(custom modes only, as both autopilots require), SET_MODE, MAV_CMD_MISSION_START,
MAV_CMD_NAV_RETURN_TO_LAUNCH and MAV_CMD_NAV_LOITER_UNLIM;
``command`` answers every COMMAND_LONG / COMMAND_INT with the MAV_RESULT the autopilot would
give: a mode it cannot fly without a pilot's sticks (manual, stabilised, acro, VTOL modes),
disarming in the air or a mission start with no mission is DENIED (PX4) or FAILED
(ArduPilot); a command it does not implement, and every effector command (servo, relay,
actuator, gripper, winch, parachute, payload), UNSUPPORTED. It never drives an effector.

Mission items are flown in order: a waypoint is reached within its acceptance radius (param 2,
at least the tightest circle the airframe can fly) and held for param 1 seconds on a circle;
LOITER_TIME circles for param 1 seconds once on the circle (radius param 3, its sign the
direction, clockwise positive); LOITER_TURNS for param 1 turns; LOITER_UNLIM for ever;
RETURN_TO_LAUNCH flies home; DO_CHANGE_SPEED sets the airspeed. MISSION_CURRENT is sent when
the current item changes (and with every heartbeat while a mission is stored),
MISSION_ITEM_REACHED when an item is done. At the mission's end PX4 keeps circling the last
item; ArduPlane switches to RTL and ArduCopter holds where it is, as they do.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.sim.kinematics import FlightState, Kinematics, wrap
from gateway.sim.mission import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_NAV_LOITER_TIME,
    MAV_CMD_NAV_LOITER_TURNS,
    MAV_CMD_NAV_LOITER_UNLIM,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_WAYPOINT,
    SimItem,
)

__all__ = ["AUTOPILOTS", "Autopilot", "AutopilotName", "Home", "Mode"]

AutopilotName = Literal["px4", "ardupilot", "arducopter"]
"""PX4 (fixed wing), ArduPilot's ArduPlane, or ArduCopter (a multirotor's HEARTBEAT and mode
numbers, flown with the same kinematics: it circles where a copter would hover)."""
AUTOPILOTS: tuple[AutopilotName, ...] = ("px4", "ardupilot", "arducopter")
Mode = Literal["orbit", "hold", "mission", "rtl"]

_STEP_S = 0.1
_MIN_SPEED_MPS, _MAX_SPEED_MPS = 10.0, 60.0
_DEFAULT_LOITER_M = 150.0
_DEFAULT_ACCEPT_M = 50.0

MAV_CMD_DO_SET_MODE = 176
MAV_CMD_MISSION_START = 300
MAV_CMD_DO_SET_MISSION_CURRENT = 224
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_REQUEST_MESSAGE = 512
_MSG_HOME_POSITION = 242
_MSG_MISSION_CURRENT = 42
#: Commands that would drive an effector: the Fischer 26E has none, and says so.
EFFECTOR_COMMANDS = frozenset(
    {
        181, 182, 183, 184,  # DO_SET_RELAY, DO_REPEAT_RELAY, DO_SET_SERVO, DO_REPEAT_SERVO
        187, 208, 209, 211,  # DO_SET_ACTUATOR, DO_PARACHUTE, DO_MOTOR_TEST, DO_GRIPPER
        30001, 30002, 42600,  # PAYLOAD_PREPARE_DEPLOY, PAYLOAD_CONTROL_DEPLOY, DO_WINCH
    }
)  # fmt: skip

#: PX4: custom_mode = main << 16 | sub << 24; AUTO (4) with its sub modes.
_PX4_AUTO = 4
_PX4_SUB: dict[int, Mode] = {3: "hold", 4: "mission", 5: "rtl"}
_PX4_CUSTOM: dict[Mode, int] = {
    "orbit": _PX4_AUTO << 16 | 3 << 24,
    "hold": _PX4_AUTO << 16 | 3 << 24,
    "mission": _PX4_AUTO << 16 | 4 << 24,
    "rtl": _PX4_AUTO << 16 | 5 << 24,
}
#: ArduPlane mode numbers flown here (CIRCLE 1, AUTO 10, RTL 11, LOITER 12, GUIDED 15).
_PLANE_MODES: dict[int, Mode] = {1: "hold", 10: "mission", 11: "rtl", 12: "hold", 15: "hold"}
_PLANE_CUSTOM: dict[Mode, int] = {"orbit": 15, "hold": 12, "mission": 10, "rtl": 11}
#: ArduCopter's (AUTO 3, GUIDED 4, LOITER 5, RTL 6, CIRCLE 7, POSHOLD 16).
_COPTER_MODES: dict[int, Mode] = {
    3: "mission",
    4: "hold",
    5: "hold",
    6: "rtl",
    7: "hold",
    16: "hold",
}
_COPTER_CUSTOM: dict[Mode, int] = {"orbit": 4, "hold": 5, "mission": 3, "rtl": 6}


@dataclass(frozen=True, slots=True)
class Home:
    """Where RTL goes: degrees, metres MSL (the ground), and the altitude it returns at."""

    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    return_alt_msl_m: float


@dataclass(slots=True)
class _Leg:
    """Progress on the current item."""

    arrived_s: float | None = None  # on the circle (loiters) or at the point (holds)
    swept_rad: float = 0.0
    last_bearing: float | None = None


class Autopilot:
    """Modes, commands and the stored mission of one simulated airframe (module docstring).

    ``orbit`` gives the deterministic orbit's state at a sim time, flown until a mode is
    commanded. ``outbox`` collects MISSION_CURRENT and MISSION_ITEM_REACHED as they happen.
    """

    def __init__(
        self,
        name: AutopilotName,
        encoder: Any,
        orbit: Callable[[float], FlightState],
        home: Home,
        cruise_mps: float,
    ) -> None:
        if name not in AUTOPILOTS:
            raise ValueError(f"autopilot: expected px4, ardupilot or arducopter, got {name!r}")
        self.name = name
        self._mav = encoder
        self._orbit = orbit
        self.home = home
        self.cruise_mps = cruise_mps
        self.mode: Mode = "orbit"
        self.flight: Kinematics | None = None
        self.t_s = 0.0
        self.items: tuple[SimItem, ...] = ()
        self.current = 0
        self.started = False
        self.complete = False
        self._leg = _Leg()
        self._hold_at: tuple[float, float, float] | None = None
        self._hold_radius_m = 0.0  # 0: the default circle
        self.outbox: list[Any] = []
        #: Commands answered, by MAV_RESULT (bounded however many arrive).
        self.answered: dict[int, int] = {}

    # -- what the airframe reports ------------------------------------------------------------

    @property
    def mav_type(self) -> int:
        """HEARTBEAT.type: a fixed wing, or ArduCopter's quadrotor."""
        copter = self.name == "arducopter"
        return int(mav.MAV_TYPE_QUADROTOR if copter else mav.MAV_TYPE_FIXED_WING)

    @property
    def mav_autopilot(self) -> int:
        """HEARTBEAT.autopilot."""
        return int(mav.MAV_AUTOPILOT_PX4 if self.name == "px4" else mav.MAV_AUTOPILOT_ARDUPILOTMEGA)

    @property
    def custom_mode(self) -> int:
        """HEARTBEAT.custom_mode of the mode flown."""
        table = {"px4": _PX4_CUSTOM, "ardupilot": _PLANE_CUSTOM}.get(self.name, _COPTER_CUSTOM)
        return table[self.mode]

    @property
    def base_mode(self) -> int:
        """HEARTBEAT.base_mode: armed, custom mode, and the automatic flags of an auto mode."""
        auto = mav.MAV_MODE_FLAG_AUTO_ENABLED | mav.MAV_MODE_FLAG_GUIDED_ENABLED
        return int(
            mav.MAV_MODE_FLAG_SAFETY_ARMED | mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            | (auto | mav.MAV_MODE_FLAG_STABILIZE_ENABLED if self.mode != "orbit" else 0)
        )  # fmt: skip

    def state(self, t_s: float) -> FlightState:
        """The flight state at sim time ``t_s`` (flying up to it first)."""
        self.advance(t_s)
        return self._orbit(t_s) if self.flight is None else self.flight.state()

    def look_point(self) -> tuple[float, float] | None:
        """Where the camera points while flying itself: the item, circle or home it flies to."""
        if self.mode == "mission" and not self.complete and self.current < len(self.items):
            item = self.items[self.current]
            if item.command == MAV_CMD_NAV_RETURN_TO_LAUNCH:
                return self.home.lat_deg, self.home.lon_deg
            if item.command != MAV_CMD_DO_CHANGE_SPEED:
                return item.lat_deg, item.lon_deg
        if self.mode == "rtl":
            return self.home.lat_deg, self.home.lon_deg
        if self._hold_at is not None:
            return self._hold_at[0], self._hold_at[1]
        return None

    def mission_current(self) -> Any:
        """MISSION_CURRENT as it stands (seq, total, mission state)."""
        if not self.items:
            state = mav.MISSION_STATE_NO_MISSION
        elif self.complete:
            state = mav.MISSION_STATE_COMPLETE
        elif self.mode == "mission":
            state = mav.MISSION_STATE_ACTIVE
        else:
            state = mav.MISSION_STATE_PAUSED if self.started else mav.MISSION_STATE_NOT_STARTED
        return self._mav.mission_current_encode(self.current, len(self.items), state)

    def drain(self) -> list[Any]:
        """The MISSION_CURRENT / MISSION_ITEM_REACHED messages due since the last call."""
        out, self.outbox = self.outbox, []
        return out

    # -- MissionHost ----------------------------------------------------------------------------

    def mission_replaced(self, items: tuple[SimItem, ...]) -> None:
        """A new mission: flown from its first item (at once if in mission mode)."""
        self.items = items
        self.current = 0
        self.complete = False
        self.started = False
        self._leg = _Leg()
        if self.mode == "mission":
            if items:
                self.started = True
            else:
                self._enter("hold")

    def set_current(self, seq: int) -> bool:
        """Make ``seq`` the current item (False, and nothing changes, if out of range)."""
        if not 0 <= seq < len(self.items):
            return False
        self.current = seq
        self.complete = False
        self._leg = _Leg()
        self.outbox.append(self.mission_current())
        return True

    # -- commands -------------------------------------------------------------------------------

    def command(self, command: int, params: tuple[float, ...], t_s: float) -> tuple[int, list[Any]]:
        """Act on a COMMAND_LONG/COMMAND_INT at sim time ``t_s``: the MAV_RESULT, and the
        messages the command asks for (REQUEST_MESSAGE)."""
        self.advance(t_s)
        p = (*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)[:7]
        extra: list[Any] = []
        if command == MAV_CMD_DO_SET_MODE:
            result = self._set_mode_command(p[0], p[1], p[2])
        elif command == MAV_CMD_MISSION_START:
            result = self._start(int(p[0]) if math.isfinite(p[0]) else 0)
        elif command == MAV_CMD_NAV_RETURN_TO_LAUNCH:
            result = self._enter("rtl")
        elif command == MAV_CMD_NAV_LOITER_UNLIM:
            result = self._enter("hold")
        elif command == MAV_CMD_DO_SET_MISSION_CURRENT:
            ok = math.isfinite(p[0]) and self.set_current(int(p[0]))
            result = mav.MAV_RESULT_ACCEPTED if ok else self._refusal
        elif command == MAV_CMD_DO_CHANGE_SPEED:
            result = self._change_speed(p[1])
        elif command == MAV_CMD_COMPONENT_ARM_DISARM:
            # Armed and flying: arming again is nothing; disarming in the air is refused.
            result = mav.MAV_RESULT_ACCEPTED if p[0] == 1 else self._refusal
        elif command == MAV_CMD_REQUEST_MESSAGE and p[0] == _MSG_HOME_POSITION:
            result = mav.MAV_RESULT_ACCEPTED
            extra.append(self.home_position())
        elif command == MAV_CMD_REQUEST_MESSAGE and p[0] == _MSG_MISSION_CURRENT:
            result = mav.MAV_RESULT_ACCEPTED
            extra.append(self.mission_current())
        else:
            result = mav.MAV_RESULT_UNSUPPORTED  # effector commands among them
        self.answered[int(result)] = self.answered.get(int(result), 0) + 1
        return int(result), extra

    def set_mode(self, base_mode: int, custom_mode: int, t_s: float) -> int:
        """SET_MODE (the message): the MAV_RESULT ArduPilot acknowledges it with."""
        self.advance(t_s)
        if self.name == "px4":
            main, sub = custom_mode >> 16 & 0xFF, custom_mode >> 24 & 0xFF
            return self._set_mode_command(float(base_mode), float(main), float(sub))
        return self._set_mode_command(float(base_mode), float(custom_mode), 0.0)

    def home_position(self) -> Any:
        """HOME_POSITION."""
        h = self.home
        return self._mav.home_position_encode(
            round(h.lat_deg * 1e7), round(h.lon_deg * 1e7), round(h.alt_msl_m * 1000),
            0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
        )  # fmt: skip

    @property
    def _refusal(self) -> int:
        return int(mav.MAV_RESULT_DENIED if self.name == "px4" else mav.MAV_RESULT_FAILED)

    def _set_mode_command(self, base: float, main: float, sub: float) -> int:
        if not (math.isfinite(base) and int(base) & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED):
            return int(mav.MAV_RESULT_UNSUPPORTED)  # both take custom modes only
        if not (math.isfinite(main) and math.isfinite(sub)):
            return self._refusal
        if self.name == "px4":
            wanted = _PX4_SUB.get(int(sub)) if int(main) == _PX4_AUTO else None
        else:
            modes = _PLANE_MODES if self.name == "ardupilot" else _COPTER_MODES
            wanted = modes.get(int(main))
        if wanted is None:
            return self._refusal  # a manual mode, a VTOL mode, or no mode at all
        if wanted == "mission":
            return self._start(None)
        return self._enter(wanted)

    def _start(self, first: int | None) -> int:
        if not self.items:
            return self._refusal
        if first is not None and not self.set_current(max(first, 0)):
            return self._refusal
        if self.complete:  # a finished mission starts over
            self.set_current(0)
        self.started = True
        return self._enter("mission")

    def _change_speed(self, speed_mps: float) -> int:
        if not (math.isfinite(speed_mps) and _MIN_SPEED_MPS <= speed_mps <= _MAX_SPEED_MPS):
            return self._refusal
        self.cruise_mps = speed_mps
        if self.flight is not None:
            self.flight.speed_mps = speed_mps
        return int(mav.MAV_RESULT_ACCEPTED)

    def _enter(self, mode: Mode) -> int:
        if self.flight is None:
            s = self._orbit(self.t_s)
            self.flight = Kinematics(s.lat_deg, s.lon_deg, s.alt_msl_m, s.track_rad, s.speed_mps)
            self.flight.turn_rps = s.turn_rps
        if mode == "hold":
            f = self.flight
            self._hold_at = (f.lat_deg, f.lon_deg, f.alt_msl_m)
            self._hold_radius_m = 0.0
        changed = mode != self.mode
        self.mode = mode
        self._leg = _Leg()
        if changed and mode == "mission":
            self.outbox.append(self.mission_current())
        if changed and mode == "rtl":
            # Where it is going, as an autopilot publishes its home when it heads there: a
            # ground station learns the home it had not asked for.
            self.outbox.append(self.home_position())
        return int(mav.MAV_RESULT_ACCEPTED)

    # -- flying ---------------------------------------------------------------------------------

    def advance(self, t_s: float) -> None:
        """Fly up to sim time ``t_s`` (never backwards)."""
        if self.flight is None:
            self.t_s = max(self.t_s, t_s)
            return
        while self.t_s < t_s - 1e-9:
            dt = min(_STEP_S, t_s - self.t_s)
            self._step(dt)
            self.t_s += dt

    def _step(self, dt: float) -> None:
        f = self.flight
        assert f is not None  # noqa: S101 - advance steps only a flown airframe
        if self.mode == "mission" and not self.complete and self.items:
            turn, alt = self._fly_item(f)
        elif self.mode == "rtl":
            turn, alt = self._circle(f, self.home.lat_deg, self.home.lon_deg, 0.0, True)
            alt = self.home.return_alt_msl_m
        else:
            lat, lon, alt = self._hold_at or (f.lat_deg, f.lon_deg, f.alt_msl_m)
            turn, _ = self._circle(f, lat, lon, self._hold_radius_m, True)
        f.step(dt, turn, alt)

    def _radius(self, f: Kinematics, wanted_m: float) -> float:
        r = abs(wanted_m) if math.isfinite(wanted_m) and wanted_m != 0 else _DEFAULT_LOITER_M
        return max(r, 1.2 * f.min_radius_m)

    def _circle(
        self, f: Kinematics, lat: float, lon: float, radius_m: float, clockwise: bool
    ) -> tuple[float, float]:
        return f.steer_orbit(lat, lon, self._radius(f, radius_m), clockwise=clockwise), f.alt_msl_m

    def _alt(self, item: SimItem) -> float:
        return item.alt_m + (self.home.alt_msl_m if item.is_relative_alt else 0.0)

    def _fly_item(self, f: Kinematics) -> tuple[float, float]:
        item = self.items[self.current]
        if item.command == MAV_CMD_DO_CHANGE_SPEED:
            self._change_speed(item.params[1])
            self._reached(f)
            return f.steer_to(*self._next_point(f)), f.alt_msl_m
        if item.command == MAV_CMD_NAV_RETURN_TO_LAUNCH:
            h = self.home
            if f.to(h.lat_deg, h.lon_deg)[0] <= self._acceptance(f, 0.0):
                self._reached(f)
            return f.steer_to(h.lat_deg, h.lon_deg), h.return_alt_msl_m
        alt = self._alt(item)
        distance_m, bearing = f.to(item.lat_deg, item.lon_deg)
        leg = self._leg
        if item.command == MAV_CMD_NAV_WAYPOINT:
            hold_s = item.params[0] if math.isfinite(item.params[0]) else 0.0
            if leg.arrived_s is None and distance_m <= self._acceptance(f, item.params[1]):
                leg.arrived_s = self.t_s
            if leg.arrived_s is None:
                return f.steer_to(item.lat_deg, item.lon_deg), alt
            if self.t_s - leg.arrived_s >= hold_s:
                self._reached(f)
                return f.steer_to(*self._next_point(f)), alt
            return f.steer_orbit(
                item.lat_deg, item.lon_deg, self._radius(f, 0.0), clockwise=True
            ), alt
        radius = self._radius(f, item.params[2])
        clockwise = not (math.isfinite(item.params[2]) and item.params[2] < 0)
        turn = f.steer_orbit(item.lat_deg, item.lon_deg, radius, clockwise=clockwise)
        on_circle = abs(distance_m - radius) <= max(25.0, 0.2 * radius)
        if leg.arrived_s is None and on_circle:
            leg.arrived_s = self.t_s
            leg.last_bearing = bearing
        if leg.arrived_s is not None and leg.last_bearing is not None:
            leg.swept_rad += abs(wrap(bearing - leg.last_bearing))
            leg.last_bearing = bearing
            if (
                item.command == MAV_CMD_NAV_LOITER_TIME
                and self.t_s - leg.arrived_s >= item.params[0]
            ) or (
                item.command == MAV_CMD_NAV_LOITER_TURNS
                and leg.swept_rad >= item.params[0] * math.tau
            ):
                self._reached(f)
        return turn, alt

    def _acceptance(self, f: Kinematics, wanted_m: float) -> float:
        given = wanted_m if math.isfinite(wanted_m) and wanted_m > 0 else _DEFAULT_ACCEPT_M
        # Never tighter than the airframe can turn: it would circle the point for ever.
        return max(given, 1.1 * f.min_radius_m)

    def _next_point(self, f: Kinematics) -> tuple[float, float]:
        """Where to head after the item just done: the next positioned item, or here."""
        for item in self.items[self.current :]:
            if item.command not in (MAV_CMD_DO_CHANGE_SPEED, MAV_CMD_NAV_RETURN_TO_LAUNCH):
                return item.lat_deg, item.lon_deg
        return f.lat_deg + math.degrees(math.cos(f.track_rad) * 1e-3), f.lon_deg + math.degrees(
            math.sin(f.track_rad) * 1e-3
        )

    def _reached(self, f: Kinematics) -> None:
        self.outbox.append(self._mav.mission_item_reached_encode(self.current))
        self._leg = _Leg()
        last = self.current + 1 >= len(self.items)
        if not last:
            self.current += 1
            self.outbox.append(self.mission_current())
            return
        self.complete = True
        item = self.items[self.current]
        self.outbox.append(self.mission_current())
        if self.name == "ardupilot":
            self._enter("rtl")  # ArduPlane: "Mission complete, changing mode to RTL"
        elif self.name == "arducopter":  # ArduCopter stays in AUTO and holds where it is
            self._hold_at = (f.lat_deg, f.lon_deg, f.alt_msl_m)
        elif item.command == MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self._hold_at = (self.home.lat_deg, self.home.lon_deg, self.home.return_alt_msl_m)
        elif item.command == MAV_CMD_DO_CHANGE_SPEED:
            self._hold_at = (f.lat_deg, f.lon_deg, f.alt_msl_m)
        else:  # PX4 circles the last item, on its own circle
            self._hold_at = (item.lat_deg, item.lon_deg, self._alt(item))
            self._hold_radius_m = 0.0 if item.command == MAV_CMD_NAV_WAYPOINT else item.params[2]
