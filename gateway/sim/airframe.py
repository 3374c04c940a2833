"""A simulated Fischer 26E that flies a circle, or its mission, and speaks real MAVLink 2.

``frames_at`` has no I/O and no clock of its own (sim time in, frames out), so tests can
compare what the gateway delivers with what was sent. ``run_udp`` paces it on the event
loop's clock and sends one frame per datagram, sealed in the tunnel when given a ``Sealer``
(and signed when the airframe has a signing key). It reads the uplink in every link mode:
it answers commands and the mission protocol as PX4 or ArduPilot would (``autopilot``;
``gateway.sim.autopilot``, ``gateway.sim.mission``) and flies what it is told, and it keeps
each FISCHER_DETECTION it sent in a ``ResendStore``, re-sending it until the gateway's
FISCHER_DETECTION_ACK for it arrives. ``answer`` is the uplink without I/O (message and times
in, replies out).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any, Protocol

import anyio
import anyio.abc
import structlog
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.domain.geodesy import distance_bearing
from gateway.fleet.dialect import FischerDetection, FischerDetectionAck, fischer_detection
from gateway.fleet.hopdialect import FischerHopSchedule
from gateway.fleet.security.signing import mavlink_timestamp_now
from gateway.sim.autopilot import Autopilot, AutopilotName, Home
from gateway.sim.datalink import AirframeLink, LinkCounts
from gateway.sim.kinematics import FlightState, quaternion
from gateway.sim.mission import MissionServer
from gateway.sim.power import power_messages
from gateway.sim.radio import SimRadio
from gateway.sim.resend import ResendPolicy, ResendStore

if TYPE_CHECKING:
    from gateway.fleet.security.tunnel import Sealer

__all__ = [
    "MessageFeed",
    "SentPosition",
    "SimProfile",
    "SimulatedAirframe",
]

log = structlog.get_logger(__name__)

_WGS84_A_M = 6_378_137.0
_WGS84_E2 = 6.694379990141317e-3
_G_MPS2 = 9.80665
_PITCH_RAD = 0.05  # angle of attack in level cruise
_MISSION_MESSAGES = frozenset(
    {
        "MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_REQUEST_LIST",
        "MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_CLEAR_ALL", "MISSION_SET_CURRENT",
    }
)  # fmt: skip
_MAV_COMP_ID_ALL = 0
_COMMANDS_KEPT = 1000
# Callers' sim times (i × step) and schedule slots (n × period) differ by float rounding.
_EPS_S = 1e-9


@dataclass(frozen=True)
class SimProfile:
    """A deterministic flight (a clockwise circle around a centre) and each message's rate.

    A rate of 0 Hz turns that message group off; detections (FISCHER_DETECTION, the project
    dialect) are off unless ``detection_hz`` is set. ``geoid_sep_m`` is added to the MSL
    altitude for ``GPS_RAW_INT.alt_ellipsoid``; ``home_alt_msl_m`` gives ``relative_alt``.
    Raises ``ValueError`` naming the field when a value is out of range.
    """

    centre_lat_deg: float = 65.8252  # Boden, Sweden
    centre_lon_deg: float = 21.6886
    radius_m: float = 400.0
    alt_msl_m: float = 250.0
    geoid_sep_m: float = 22.0
    speed_mps: float = 22.0
    position_hz: float = 10.0
    status_hz: float = 2.0
    gps_hz: float = 5.0
    heartbeat_hz: float = 1.0
    detection_hz: float = 0.0
    battery_wh: float = 600.0
    power_w: float = 355.0
    home_alt_msl_m: float = 150.0
    hop_event_hz: float = 2.0  # FISCHER_HOP_EVENT reports, only while a hop schedule is active
    #: CAMERA_FOV_STATUS and GIMBAL_DEVICE_ATTITUDE_STATUS: a camera looking at the centre.
    camera_hz: float = 0.0

    def __post_init__(self) -> None:
        positive = {"radius_m", "speed_mps", "battery_wh", "power_w"}
        rates = {
            "position_hz", "status_hz", "gps_hz", "heartbeat_hz", "detection_hz", "hop_event_hz",
            "camera_hz",
        }  # fmt: skip
        for f in fields(self):
            value = getattr(self, f.name)
            if not math.isfinite(value):
                expected = "a finite number"
            elif f.name in positive and value <= 0:
                expected = "> 0"
            elif f.name in rates and value < 0:
                expected = ">= 0"
            elif f.name == "centre_lat_deg" and abs(value) >= 89.0:
                expected = "within ±89°"
            else:
                continue
            raise ValueError(f"SimProfile.{f.name}: expected {expected}, got {value!r}")


_DEFAULT_PROFILE = SimProfile()
_DEFAULT_RESEND = ResendPolicy()


@dataclass(frozen=True, slots=True)
class SentPosition:
    """A GLOBAL_POSITION_INT as sent, in wire units."""

    time_boot_ms: int
    lat_e7: int
    lon_e7: int
    alt_mm: int


@dataclass(slots=True)
class _Schedule:
    period_s: float  # inf when the group is off
    emit: Callable[[float], list[Any]]
    # Slots are origin + n × period: multiplying, not adding, keeps them on the grid.
    origin_s: float = 0.0
    slot: int = 0

    @property
    def next_s(self) -> float:
        if math.isinf(self.period_s):
            return math.inf
        return self.origin_s + self.slot * self.period_s


class MessageFeed(Protocol):
    """More messages for an airframe to send (a scenario's detections), on its own timeline."""

    def next_due_s(self) -> float:
        """The sim time of the next message (inf if none)."""
        ...

    def messages_at(self, t_s: float, unix_s: float) -> list[Any]:
        """The pymavlink messages due by sim time ``t_s``; ``unix_s`` is its UTC (UNIX) time."""
        ...


class SimulatedAirframe:
    """One airframe: its MAVLink encoder, flight profile and message schedule.

    ``sent_positions`` keeps the last ``position_history`` GLOBAL_POSITION_INTs produced.
    ``feed`` adds messages from elsewhere (a scenario's detections) to the same MAVLink
    stream, in the same sequence numbering. ``resend`` is how unacknowledged detections are
    re-sent (None: never, for a gateway that does not acknowledge). With ``signing_key``
    (32 bytes) every frame is signed and only validly signed uplink frames are read.
    ``autopilot`` (``px4``, ``ardupilot`` or ``arducopter``) is whose HEARTBEAT, modes and
    command answers it gives; home is the orbit's centre on the ground (``home_alt_msl_m``).
    """

    def __init__(
        self,
        sysid: int,
        profile: SimProfile = _DEFAULT_PROFILE,
        *,
        phase_rad: float = 0.0,
        position_history: int = 100_000,
        feed: MessageFeed | None = None,
        resend: ResendPolicy | None = _DEFAULT_RESEND,
        signing_key: bytes | None = None,
        autopilot: AutopilotName = "ardupilot",
    ) -> None:
        if not 1 <= sysid <= 255:
            raise ValueError(f"sysid: expected 1..255, got {sysid!r}")
        self.sysid = sysid
        self.profile = profile
        self.phase_rad = phase_rad
        self._mav = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
        p = profile
        # Local radii of curvature of WGS84 at the centre: metres to degrees on the circle.
        s2 = math.sin(math.radians(p.centre_lat_deg)) ** 2
        self._m_per_rad_lat = _WGS84_A_M * (1 - _WGS84_E2) / (1 - _WGS84_E2 * s2) ** 1.5
        self._m_per_rad_lon = (
            _WGS84_A_M / math.sqrt(1 - _WGS84_E2 * s2) * math.cos(math.radians(p.centre_lat_deg))
        )
        self._omega_rps = p.speed_mps / p.radius_m
        self._bank_rad = math.atan(p.speed_mps**2 / (p.radius_m * _G_MPS2))
        self._schedules = [
            _Schedule(_period(p.heartbeat_hz), self._heartbeat),
            _Schedule(_period(p.position_hz), self._position),
            _Schedule(_period(p.gps_hz), self._gps),
            _Schedule(_period(p.status_hz), self._status),
            _Schedule(_period(p.detection_hz), self._detection),
            _Schedule(_period(p.camera_hz), self._camera),
        ]
        # Hop reports are due only while the radio hops on a schedule (see next_due_s).
        self._hop_schedule = _Schedule(_period(p.hop_event_hz), self._hop_events)
        self._schedules.append(self._hop_schedule)
        #: More messages on the same stream (a scenario's detections); settable once built.
        self.feed = feed
        #: UNIX time of sim time 0, for FISCHER_DETECTION.time_usec (``run_udp`` sets it).
        self.boot_unix_s = 0.0
        #: Sim seconds per real second (``run_udp`` sets it): sim time t is UNIX time
        #: ``boot_unix_s + t / speed``.
        self.speed = 1.0
        self._detections = 0
        self.sent_positions: deque[SentPosition] = deque(maxlen=position_history)
        self.frames_sent = 0
        #: Answer COMMAND_LONG with COMMAND_ACK (MAV_RESULT_ACCEPTED); False plays a lost uplink.
        self.ack_commands = True
        #: (command id, confirmation) of the last 1000 COMMAND_LONG / COMMAND_INT for us.
        self.commands: list[tuple[int, int]] = []
        self._parser = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self._parser.robust_parsing = True
        if signing_key is not None:
            stamp = mavlink_timestamp_now(time.time())
            for end in (self._mav, self._parser):
                end.signing.secret_key = signing_key
                end.signing.timestamp = stamp
            self._mav.signing.sign_outgoing = True
        #: The detections sent and not yet acknowledged, and what became of them all.
        self.resend = ResendStore(sysid, resend)
        #: What the UDP link saw (refusals while nothing listened, uplink rejected).
        self.link = LinkCounts()
        self._acked: anyio.Event | None = None  # set by each acknowledgement, wakes the sender
        #: The AD9361: answers FISCHER_HOP_SCHEDULE, reports hops while a schedule is active.
        self.radio = SimRadio(sysid)
        home = Home(p.centre_lat_deg, p.centre_lon_deg, p.home_alt_msl_m, p.alt_msl_m)
        #: Modes, commands and the mission flown (the orbit until a mode is commanded).
        self.autopilot = Autopilot(autopilot, self._mav, self._orbit_state, home, p.speed_mps)
        #: The mission protocol: uploads, downloads, clearing.
        self.missions = MissionServer(sysid, self.autopilot, self._mav)
        self._origin_s = 0.0  # loop time of sim time 0 (``run_udp``)
        self._mission_wake: anyio.Event | None = None

    def frames_at(self, t_s: float) -> list[bytes]:
        """The frames due at sim time ``t_s`` (seconds since boot), in a fixed order.

        Each message group is emitted when its period has elapsed since it was last due;
        all are due at the first call. Calls must not go back in time. After a gap longer
        than a period the missed slots are skipped, not sent in a burst. No I/O, no clock.
        """
        return [self._pack(msg) for msg in self.messages_at(t_s)]

    def messages_at(self, t_s: float) -> list[Any]:
        """The messages ``frames_at(t_s)`` would pack, as pymavlink message objects."""
        self.autopilot.advance(t_s)
        messages: list[Any] = []
        for schedule in self._schedules:
            if t_s + _EPS_S < schedule.next_s:
                continue
            schedule.slot += 1
            if schedule.next_s <= t_s + _EPS_S:
                schedule.origin_s, schedule.slot = t_s, 1
            messages.extend(schedule.emit(t_s))
        if self.feed is not None and self.feed.next_due_s() <= t_s + _EPS_S:
            messages.extend(self.feed.messages_at(t_s, self.unix_s(t_s)))
        messages.extend(self.autopilot.drain())
        return messages

    def _pack(self, msg: Any) -> bytes:
        frame = bytes(msg.pack(self._mav))
        # pack() does not advance the sequence number (send() would); receivers count gaps
        # in it as loss. A re-send is a new frame, so it takes the next number too.
        self._mav.seq = (self._mav.seq + 1) % 256
        return frame

    def summary(self) -> str:
        """One line: what became of the detections, and what the link refused or rejected."""
        counts = self.resend.counts
        off = "" if self.resend.policy is not None else " (re-send off)"
        return (
            f"detections sent {counts.sent}, re-sent {counts.resent}, acknowledged "
            f"{counts.acknowledged}, dropped {counts.dropped}, unacknowledged "
            f"{len(self.resend)}{off}; sends refused {self.link.refused}, uplink rejected "
            f"{self.link.uplink_rejected}"
        )

    def autopilot_summary(self) -> str | None:
        """One line on missions and commands, or None if the airframe was never tasked."""
        pilot, missions = self.autopilot, self.missions
        refused = sum(missions.refused.values())
        if not (missions.accepted or refused or pilot.answered):
            return None
        accepted = pilot.answered.get(int(mav.MAV_RESULT_ACCEPTED), 0)
        done = ", complete" if pilot.complete else ""
        return (
            f"autopilot {pilot.name}: missions accepted {missions.accepted}, refused {refused};"
            f" commands answered {sum(pilot.answered.values())}, accepted {accepted}; mode"
            f" {pilot.mode}, item {pilot.current} of {len(pilot.items)}{done}"
        )

    def next_due_s(self) -> float:
        """The sim time at which ``frames_at`` will next return frames (inf if never)."""
        due = min(
            schedule.next_s
            for schedule in self._schedules
            if schedule is not self._hop_schedule or self.radio.active is not None
        )
        return due if self.feed is None else min(due, self.feed.next_due_s())

    def unix_s(self, t_s: float) -> float:
        """The UNIX time of sim time ``t_s`` (the real time it is sent)."""
        return self.boot_unix_s + t_s / self.speed

    def position_at(self, t_s: float) -> tuple[float, float]:
        """Latitude and longitude (degrees) at sim time ``t_s``: on the orbit until a mode is
        commanded, then as flown (which moves the flight on to ``t_s``: never go back)."""
        state = self.autopilot.state(t_s)
        return state.lat_deg, state.lon_deg

    def _orbit_state(self, t_s: float) -> FlightState:
        p = self.profile
        lat_deg, lon_deg, track_rad = self._state(t_s)
        return FlightState(
            lat_deg, lon_deg, p.alt_msl_m, track_rad, p.speed_mps, self._omega_rps, 0.0,
            self._bank_rad,
        )  # fmt: skip

    def _state(self, t_s: float) -> tuple[float, float, float]:
        """Latitude and longitude (degrees), and track (radians from north, clockwise)."""
        p = self.profile
        theta = self.phase_rad + self._omega_rps * t_s  # bearing of the airframe from the centre
        north_m, east_m = p.radius_m * math.cos(theta), p.radius_m * math.sin(theta)
        return (
            p.centre_lat_deg + math.degrees(north_m / self._m_per_rad_lat),
            p.centre_lon_deg + math.degrees(east_m / self._m_per_rad_lon),
            (theta + math.pi / 2) % math.tau,
        )

    def _heartbeat(self, _t_s: float) -> list[Any]:
        pilot = self.autopilot
        heartbeat = self._mav.heartbeat_encode(
            pilot.mav_type, pilot.mav_autopilot, pilot.base_mode, pilot.custom_mode,
            mav.MAV_STATE_ACTIVE,
        )  # fmt: skip
        # PX4 and ArduPilot report the mission's state steadily, not only as it changes.
        return [heartbeat, pilot.mission_current()] if pilot.items else [heartbeat]

    def _position(self, t_s: float) -> list[Any]:
        p = self.profile
        s = self.autopilot.state(t_s)
        track_rad = s.track_rad
        boot_ms = round(t_s * 1000) % 2**32
        lat_e7, lon_e7 = round(s.lat_deg * 1e7), round(s.lon_deg * 1e7)
        alt_mm = round(s.alt_msl_m * 1000)
        self.sent_positions.append(SentPosition(boot_ms, lat_e7, lon_e7, alt_mm))
        vx = round(s.speed_mps * math.cos(track_rad) * 100)
        vy = round(s.speed_mps * math.sin(track_rad) * 100)
        vz = round(-s.climb_mps * 100)
        hdg = round(math.degrees(track_rad) * 100) % 36000
        rel_mm = round((s.alt_msl_m - p.home_alt_msl_m) * 1000)
        yaw = (track_rad + math.pi) % math.tau - math.pi
        # A coordinated level turn: the wing down on the inside, body rates from the turn rate.
        bank, omega = s.bank_rad, s.turn_rps
        return [
            self._mav.global_position_int_encode(
                boot_ms, lat_e7, lon_e7, alt_mm, rel_mm, vx, vy, vz, hdg
            ),
            self._mav.attitude_encode(
                boot_ms, bank, _PITCH_RAD, yaw, 0.0, omega * math.sin(bank), omega * math.cos(bank)
            ),
        ]

    def _gps(self, t_s: float) -> list[Any]:
        p = self.profile
        s = self.autopilot.state(t_s)
        alt_mm = round(s.alt_msl_m * 1000)
        track_deg = math.degrees(s.track_rad)
        gps = self._mav.gps_raw_int_encode(
            round(t_s * 1e6), mav.GPS_FIX_TYPE_3D_FIX,
            round(s.lat_deg * 1e7), round(s.lon_deg * 1e7), alt_mm,
            80, 120, round(s.speed_mps * 100), round(track_deg * 100) % 36000, 17,
            alt_ellipsoid=alt_mm + round(p.geoid_sep_m * 1000), h_acc=1200, v_acc=2000,
            vel_acc=300,
        )  # fmt: skip
        hud = self._mav.vfr_hud_encode(
            s.speed_mps, s.speed_mps, round(track_deg) % 360, 55, s.alt_msl_m, s.climb_mps
        )
        return [gps, hud]

    def _detection(self, t_s: float) -> list[Any]:
        # A target 1 km north of the orbit's centre, alternating a tank and a hostile UAV.
        p = self.profile
        self._detections += 1
        is_tank = self._detections % 2 == 1
        lat = p.centre_lat_deg + math.degrees(1000.0 / self._m_per_rad_lat)
        return [
            fischer_detection(
                time_usec=round(self.unix_s(t_s) * 1e6),
                detection_id=self._detections,
                lat_e7=round(lat * 1e7),
                lon_e7=round(p.centre_lon_deg * 1e7),
                alt_msl_m=p.home_alt_msl_m if is_tank else p.alt_msl_m,
                sigma_h_m=8.0 if is_tank else 25.0,
                class_id=1 if is_tank else 4,
                sensor=1 if is_tank else 2,  # IR for the tank, RF for the UAV
                confidence_pct=91 if is_tank else 78,
                subtype="T-72" if is_tank else "",
                frame_size=1,  # the only detection of its sensor frame
            )
        ]

    def _hop_events(self, t_s: float) -> list[Any]:
        return list(self.radio.events_at(self.unix_s(t_s)))

    def _camera(self, t_s: float) -> list[Any]:
        # The gimbal holds the orbit's centre (on the ground at home altitude) in view: to the
        # right of the clockwise circle, looking down at the angle the height and radius give.
        p = self.profile
        look = self.autopilot.look_point()
        if look is None:
            lat_deg, lon_deg, track_rad = self._state(t_s)
            alt_msl_m = p.alt_msl_m
            depression = math.atan2(p.alt_msl_m - p.home_alt_msl_m, p.radius_m)
            yaw = track_rad + math.pi / 2  # absolute bearing to the centre
            relative_yaw = math.pi / 2
            look = (p.centre_lat_deg, p.centre_lon_deg)
        else:  # flying itself: the camera holds what it flies to
            s = self.autopilot.state(t_s)
            lat_deg, lon_deg, alt_msl_m = s.lat_deg, s.lon_deg, s.alt_msl_m
            distance_m, bearing_deg = distance_bearing(lat_deg, lon_deg, *look)
            depression = math.atan2(alt_msl_m - p.home_alt_msl_m, max(distance_m, 1.0))
            yaw = math.radians(bearing_deg)
            relative_yaw = yaw - s.track_rad
        boot_ms = round(t_s * 1000) % 2**32
        gimbal = quaternion(0.0, -depression, relative_yaw)  # yaw relative to the nose
        camera = quaternion(0.0, -depression, yaw)
        return [
            self._mav.gimbal_device_attitude_status_encode(
                0, 0, boot_ms, mav.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME, gimbal,
                math.nan, math.nan, math.nan, 0,
            ),
            self._mav.camera_fov_status_encode(
                boot_ms, round(lat_deg * 1e7), round(lon_deg * 1e7), round(alt_msl_m * 1000),
                round(look[0] * 1e7), round(look[1] * 1e7),
                round(p.home_alt_msl_m * 1000), camera, 12.5, 7.0,
            ),
        ]  # fmt: skip

    def _status(self, t_s: float) -> list[Any]:
        return power_messages(self._mav, self.profile, t_s)

    async def run_udp(
        self,
        host: str,
        port: int,
        *,
        duration_s: float | None = None,
        speed: float = 1.0,
        sealer: Sealer | None = None,
        linger_s: float = 0.0,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Fly from sim time 0, sending each frame as one UDP datagram to ``host:port``.

        Pacing follows ``anyio.current_time()``: sim time ``t`` is sent at ``start + t / speed``.
        Re-sends of unacknowledged detections follow the same clock, in real seconds. The
        uplink is read throughout. A gateway that is down (sends refused) or silent is not an
        error: the airframe flies on and counts. ``task_status.started()`` is called once the
        socket exists. Returns after ``duration_s`` of sim time (never if None), after waiting
        up to ``linger_s`` real seconds for the acknowledgements of the detections still held
        if the gateway has acknowledged any at all. Cancellation-safe. Raises ``ValueError``
        for a speed or linger out of range, ``OSError`` if the socket cannot open.
        """
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed: expected a positive finite number, got {speed!r}")
        if not (math.isfinite(linger_s) and linger_s >= 0):
            raise ValueError(f"linger_s: expected a finite number >= 0, got {linger_s!r}")
        async with (
            await AirframeLink.connect(host, port, sealer=sealer, counts=self.link) as link,
            anyio.create_task_group() as tg,
        ):
            self._origin_s = anyio.current_time()
            tg.start_soon(self._read_uplink, link)
            tg.start_soon(self._mission_timer, link)
            task_status.started()
            start = self._origin_s = anyio.current_time()
            self.boot_unix_s = time.time()
            self.speed = speed
            end_s = math.inf if duration_s is None else duration_s + _EPS_S
            t_s = 0.0
            while t_s <= end_s:
                await self._send_new(link, t_s)
                t_s = min(self.next_due_s(), end_s + _EPS_S)
                await self._resend_until(link, start + t_s / speed)
            if linger_s > 0 and self.resend.has_heard_ack:
                with anyio.move_on_after(linger_s):
                    await self._resend_until(link, math.inf, until_empty=True)
            tg.cancel_scope.cancel()
        log.debug(
            "simulation_finished",
            sysid=self.sysid,
            frames_sent=self.frames_sent,
            detections_sent=self.resend.counts.sent,
            unacknowledged=len(self.resend),
        )

    async def _send_new(self, link: AirframeLink, t_s: float) -> None:
        for msg in self.messages_at(t_s):
            frame = self._pack(msg)
            if isinstance(msg, FischerDetection):
                dropped = self.resend.counts.dropped
                self.resend.add(msg, anyio.current_time())
                if dropped == 0 and self.resend.counts.dropped:
                    log.warning("detections_dropped", sysid=self.sysid, reason="re-send store full")
            if await link.send(frame):
                self.frames_sent += 1

    async def _resend(self, link: AirframeLink) -> None:
        for msg in self.resend.take_due(anyio.current_time()):
            if await link.send(self._pack(msg)):
                self.frames_sent += 1

    async def _resend_until(
        self, link: AirframeLink, until: float, *, until_empty: bool = False
    ) -> None:
        """Re-send what falls due until loop time ``until`` (or, with ``until_empty``, until
        nothing is held). An acknowledgement wakes it: the first one can start re-sending."""
        while not (until_empty and not self.resend):
            acked = self._acked = anyio.Event()
            with anyio.move_on_after(min(until, self.resend.next_due_s()) - anyio.current_time()):
                await acked.wait()
            await self._resend(link)
            if anyio.current_time() >= until:
                return

    async def _read_uplink(self, link: AirframeLink) -> None:
        """Read what the gateway sends: acknowledgements of our detections, hop schedules,
        commands, mode changes and the mission protocol (``answer``)."""
        while True:
            payload = await link.receive()
            try:
                messages = self._parser.parse_buffer(payload) or []
            except mav.MAVError:
                continue
            for msg in messages:
                if isinstance(msg, FischerDetectionAck):
                    self.resend.acknowledge(msg)
                    if self._acked is not None:
                        self._acked.set()
                    continue
                if isinstance(msg, FischerHopSchedule):
                    answer = self.radio.answer(msg, time.time())
                    replies = [] if answer is None else [answer]
                else:
                    t_s = (anyio.current_time() - self._origin_s) * self.speed
                    replies = self.answer(msg, t_s, anyio.current_time())
                    if msg.get_type() in _MISSION_MESSAGES and self._mission_wake is not None:
                        self._mission_wake.set()
                for reply in replies:
                    if await link.send(self._pack(reply)):
                        self.frames_sent += 1

    async def _mission_timer(self, link: AirframeLink) -> None:
        """Re-request a mission item the gateway did not send in time; cancel after retries."""
        while True:
            wake = self._mission_wake = anyio.Event()
            with anyio.move_on_after(self.missions.next_deadline_s() - anyio.current_time()):
                await wake.wait()
            for reply in self.missions.poll(anyio.current_time()):
                if await link.send(self._pack(reply)):
                    self.frames_sent += 1

    def answer(self, msg: Any, t_s: float, now_s: float) -> list[Any]:
        """The replies to one uplink message at sim time ``t_s`` and monotonic ``now_s``.

        COMMAND_LONG and COMMAND_INT for us get a COMMAND_ACK (unless ``ack_commands`` is
        False, which plays the command lost: nothing happens), SET_MODE too (ArduPilot
        acknowledges it as command 11, the message's id; PX4 as DO_SET_MODE); the mission
        protocol goes to ``missions``. Anything else, or for another system, gets nothing.
        Never raises on a message's values.
        """
        name = msg.get_type()
        if name in _MISSION_MESSAGES:
            self.autopilot.advance(t_s)
            return self.missions.handle(msg, now_s)
        if int(getattr(msg, "target_system", -1)) != self.sysid or int(
            getattr(msg, "target_component", _MAV_COMP_ID_ALL)
        ) not in (_MAV_COMP_ID_ALL, 1):
            return []
        to = {"target_system": msg.get_srcSystem(), "target_component": msg.get_srcComponent()}
        if name in ("COMMAND_LONG", "COMMAND_INT"):
            command = int(msg.command)
            self.commands.append((command, int(getattr(msg, "confirmation", 0))))
            if len(self.commands) > _COMMANDS_KEPT:
                del self.commands[:-_COMMANDS_KEPT]
            if not self.ack_commands:
                return []
            params = (msg.param1, msg.param2, msg.param3, msg.param4)
            result, extra = self.autopilot.command(command, tuple(map(float, params)), t_s)
            return [self._mav.command_ack_encode(command, result, **to), *extra]
        if name == "SET_MODE":
            result = self.autopilot.set_mode(int(msg.base_mode), int(msg.custom_mode), t_s)
            acked = 176 if self.autopilot.name == "px4" else mav.MAVLINK_MSG_ID_SET_MODE
            return [self._mav.command_ack_encode(acked, result, **to)]
        return []


def _period(rate_hz: float) -> float:
    return 1.0 / rate_hz if rate_hz > 0 else math.inf
