"""The fleet's airframe commander: commands, mission uploads and mission progress on MAVLink.

``FleetCommander`` implements ``gateway.flow.tasking.AirframeCommander`` over the airframe
sessions: it takes intents (upload these mission steps, start the mission, return to base)
and chooses the MAVLink for them (``gateway.fleet.missionitems``: the items, and the modes of
the airframe's autopilot: its ``autopilot`` in the config; else the one its HEARTBEAT names,
PX4 or ArduPilot, with ArduCopter's numbers for a multirotor; else the caller's
``ModeCommands``, PX4 modes or plain MAVLink commands). Commands go through
``AirframeSession.command_long`` (COMMAND_ACK correlated, retried). A mission goes up with
MAVLink's mission protocol: MISSION_COUNT, then each MISSION_ITEM_INT the airframe asks for
(MISSION_REQUEST_INT, or MISSION_REQUEST from older autopilots), until its MISSION_ACK. A
step that gets no answer within ``timeout_s`` sends MISSION_COUNT again (the airframe starts
over), at most ``retries`` times. Items are answered from the message handler (synchronous,
on ingest's path) through a bounded queue that ``run`` sends from. MISSION_CURRENT and
MISSION_ITEM_REACHED are passed to the listeners as progress; HOME_POSITION is kept. A
mission is read back (after a restart) with MISSION_REQUEST_LIST, MISSION_COUNT, then a
MISSION_REQUEST_INT per item answered by its MISSION_ITEM_INT, and a closing MISSION_ACK. Only
messages addressed to the gateway (or broadcast) count, never a ground station's.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from contextlib import suppress
from dataclasses import dataclass, field
from typing import Literal

import anyio
import anyio.abc
import structlog
from anyio.streams.memory import MemoryObjectSendStream

from gateway.domain.mission import Loiter, MissionStep, ModeCommands, Outcome, Waypoint
from gateway.errors import FrameError, LinkError
from gateway.fleet.mavlink import MavMessage, dialect
from gateway.fleet.missionitems import (
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_MISSION_START,
    MAV_CMD_NAV_LOITER_TIME,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL,
    Autopilot,
    MissionItem,
    Vehicle,
    mission_item,
    return_command,
    start_command,
)
from gateway.fleet.session import GATEWAY_COMPID, GATEWAY_SYSID, AirframeSession

__all__ = ["FleetCommander"]

log = structlog.get_logger(__name__)

MissionListener = Callable[[str, Literal["current", "reached"], int], None]

_MISSION_RESULT_NAMES: dict[int, str] = {
    int(key): str(entry.name) for key, entry in dialect.enums["MAV_MISSION_RESULT"].items()
}
_MAX_ITEMS = 500
#: The only commands and mission items this port ever sends: reconnaissance never arms,
#: releases, moves a servo or actuator, or sets a parameter, whatever a caller asks for.
_COMMANDS = frozenset({MAV_CMD_DO_SET_MODE, MAV_CMD_MISSION_START, MAV_CMD_NAV_RETURN_TO_LAUNCH})
_ITEMS = frozenset({MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LOITER_TIME})
#: DO_SET_MODE's base mode may only say "custom mode": never MAV_MODE_FLAG_SAFETY_ARMED.
_CUSTOM_MODE_ONLY = 1.0
_QUEUE_MAX = 256
_MAV_AUTOPILOT_ARDUPILOTMEGA = 3
_MAV_AUTOPILOT_PX4 = 12
_MAV_AUTOPILOT_INVALID = 8
#: MAV_TYPEs ArduCopter flies (quad, coaxial, heli, hexa, octo, tri, dodeca, decarotor).
_COPTER_TYPES = frozenset({2, 3, 4, 13, 14, 15, 29, 35})


@dataclass(slots=True)
class _Upload:
    items: Sequence[MissionItem]
    moved: anyio.Event = field(default_factory=anyio.Event)
    acked: int | None = None
    sent: set[int] = field(default_factory=set)


@dataclass(slots=True)
class _Download:
    count: int | None = None
    items: dict[int, MavMessage] = field(default_factory=dict)
    moved: anyio.Event = field(default_factory=anyio.Event)


def _step(seq: int, msg: MavMessage) -> MissionStep | str:
    """The mission step a downloaded MISSION_ITEM_INT is, or what makes it none of ours."""
    command = int(msg.command)
    lat, lon, alt = msg.x / 1e7, msg.y / 1e7, float(msg.z)
    if int(msg.frame) != MAV_FRAME_GLOBAL or command not in _ITEMS:
        return f"item {seq} is command {command} in frame {int(msg.frame)}"
    if command == MAV_CMD_NAV_LOITER_TIME:
        return Loiter(lat, lon, alt, float(msg.param1), float(msg.param3))
    return Waypoint(lat, lon, alt)


def _for_us(msg: MavMessage) -> bool:
    system = int(getattr(msg, "target_system", 0) or 0)
    component = int(getattr(msg, "target_component", 0) or 0)
    return system in (0, GATEWAY_SYSID) and component in (0, GATEWAY_COMPID)


class FleetCommander:
    """Tasks the airframes of ``sessions``; ``linked(airframe)`` says whether one can hear us."""

    def __init__(
        self, sessions: Mapping[str, AirframeSession], linked: Callable[[str], bool]
    ) -> None:
        self._sessions = sessions
        self._linked = linked
        self._uploads: dict[str, _Upload] = {}
        self._downloads: dict[str, _Download] = {}
        self._homes: dict[str, tuple[float, float]] = {}
        self._listeners: list[MissionListener] = []
        self._locks: dict[str, anyio.Lock] = {}
        self._queue: MemoryObjectSendStream[tuple[AirframeSession, bytes]] | None = None
        #: (HEARTBEAT.autopilot, HEARTBEAT.type) each airframe's flight controller last sent.
        self._heard: dict[str, tuple[int, int]] = {}
        for session in sessions.values():
            session.on("HEARTBEAT", self._on_heartbeat)
            for name in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
                session.on(name, self._on_request)
            session.on("MISSION_ACK", self._on_ack)
            session.on("MISSION_COUNT", self._on_count)
            session.on("MISSION_ITEM_INT", self._on_item)
            session.on("MISSION_CURRENT", self._on_progress)
            session.on("MISSION_ITEM_REACHED", self._on_progress)
            session.on("HOME_POSITION", self._on_home)

    def is_known(self, airframe: str) -> bool:
        """True if ``airframe`` is configured."""
        return airframe in self._sessions

    def is_linked(self, airframe: str) -> bool:
        """True if ``airframe`` has an active link and its modes are known: its flight
        controller's HEARTBEAT was heard since the gateway started (which autopilot, plane or
        copter), or its config names an autopilot whose numbers need neither (``px4``,
        ``mavlink``). Position and battery state can come before the first HEARTBEAT (after a
        restart, or as the link comes up): an order started then would get the fallback's
        mode numbers (PX4's to an ArduPilot: refused)."""
        session = self._sessions.get(airframe)
        if session is None or not self._linked(airframe):
            return False
        return airframe in self._heard or session.config.autopilot in ("px4", "mavlink")

    def home(self, airframe: str) -> tuple[float, float] | None:
        """The home (lat, lon) the airframe last reported, if any."""
        return self._homes.get(airframe)

    def on_mission(self, listener: MissionListener) -> None:
        """Tell ``listener`` of every airframe's mission progress."""
        self._listeners.append(listener)

    async def upload_mission(
        self, airframe: str, steps: Sequence[MissionStep], *, timeout_s: float, retries: int
    ) -> Outcome:
        """Upload ``steps`` as the airframe's mission, one MAVLink item per step."""
        items = [mission_item(step) for step in steps]
        return await self.upload_items(airframe, items, timeout_s=timeout_s, retries=retries)

    async def download_mission(
        self, airframe: str, *, timeout_s: float, retries: int
    ) -> tuple[Outcome, tuple[MissionStep, ...]]:
        """Read the airframe's mission back (see the module docstring)."""
        session = self._sessions[airframe]
        lock = self._locks.setdefault(airframe, anyio.Lock())
        try:
            async with lock:
                return await self._download(session, timeout_s, retries)
        except (LinkError, FrameError) as exc:
            return Outcome(False, f"not sent: {exc}", 0), ()

    async def _download(
        self, session: AirframeSession, timeout_s: float, retries: int
    ) -> tuple[Outcome, tuple[MissionStep, ...]]:
        down = _Download()
        self._downloads[session.id] = down
        target = session.config.sysid
        attempts = 0
        silent = 0  # requests in a row that got no answer: a step gets 1 + retries
        try:
            while (down.count is None or len(down.items) < down.count) and silent <= retries:
                attempts += 1
                silent += 1
                had = (down.count, len(down.items))
                if down.count is None:
                    frame = session.pack("mission_request_list", target, 1, 0)
                else:
                    missing = min(set(range(down.count)) - set(down.items))
                    frame = session.pack("mission_request_int", target, 1, missing, 0)
                down.moved = anyio.Event()
                await session.send(frame)
                with anyio.move_on_after(timeout_s):
                    await down.moved.wait()
                if (down.count, len(down.items)) != had:
                    silent = 0
        finally:
            del self._downloads[session.id]
        if down.count is None:
            return Outcome(False, f"no MISSION_COUNT after {attempts} requests", attempts), ()
        if len(down.items) < down.count:
            got = f"{len(down.items)} of {down.count} items"
            return Outcome(
                False, f"mission download: {got} after {attempts} requests", attempts
            ), ()
        with suppress(LinkError, FrameError):
            await session.send(session.pack("mission_ack", target, 1, 0, 0))
        steps: list[MissionStep] = []
        for seq in range(down.count):
            step = _step(seq, down.items[seq])
            if isinstance(step, str):
                return Outcome(False, step, attempts), ()
            steps.append(step)
        return Outcome(True, f"{down.count} items", attempts), tuple(steps)

    async def start_mission(
        self,
        airframe: str,
        items: int,
        mode_commands: ModeCommands,
        *,
        timeout_s: float,
        retries: int,
    ) -> Outcome:
        """Start the uploaded mission of ``items`` items in the airframe's autopilot's way
        (``mode_commands`` when neither the config nor its HEARTBEAT names it)."""
        command, params = start_command(*self._autopilot(airframe, mode_commands, items))
        return await self.command(airframe, command, params, timeout_s=timeout_s, retries=retries)

    async def return_to_base(
        self, airframe: str, mode_commands: ModeCommands, *, timeout_s: float, retries: int
    ) -> Outcome:
        """Send the airframe home (its autopilot's return), as for ``start_mission``."""
        autopilot, _, vehicle = self._autopilot(airframe, mode_commands, 0)
        command, params = return_command(autopilot, vehicle)
        return await self.command(airframe, command, params, timeout_s=timeout_s, retries=retries)

    def autopilot(self, airframe: str, fallback: ModeCommands) -> tuple[Autopilot, Vehicle]:
        """Whose modes task ``airframe``: its config's ``autopilot``, else the autopilot its
        HEARTBEAT names (PX4, or ArduPilot: copter numbers for a multirotor), else
        ``fallback``."""
        autopilot, _, vehicle = self._autopilot(airframe, fallback, 0)
        return autopilot, vehicle

    def _autopilot(
        self, airframe: str, fallback: ModeCommands, items: int
    ) -> tuple[Autopilot, int, Vehicle]:
        heard_autopilot, heard_type = self._heard.get(airframe, (None, None))
        vehicle: Vehicle = "copter" if heard_type in _COPTER_TYPES else "plane"
        session = self._sessions.get(airframe)
        configured = None if session is None else session.config.autopilot
        if configured is not None:
            return configured, items, vehicle
        if heard_autopilot == _MAV_AUTOPILOT_PX4:
            return "px4", items, vehicle
        if heard_autopilot == _MAV_AUTOPILOT_ARDUPILOTMEGA:
            return "ardupilot", items, vehicle
        return fallback, items, vehicle

    async def command(
        self,
        airframe: str,
        command: int,
        params: Sequence[float],
        *,
        timeout_s: float,
        retries: int,
    ) -> Outcome:
        """COMMAND_LONG ``command`` with ``params``; ok only when the ACK says ACCEPTED.

        A link that cannot carry it (down, no peer, unsignable) is an outcome, not an error.
        A command outside the reconnaissance set (``_COMMANDS``; DO_SET_MODE only with the
        custom-mode flag, never the armed one) is refused and never sent.
        """
        if command not in _COMMANDS or (
            command == MAV_CMD_DO_SET_MODE and (params[:1] or (0.0,))[0] != _CUSTOM_MODE_ONLY
        ):
            log.error("command_refused", airframe=airframe, command=command)
            return Outcome(False, f"command {command} refused: not a reconnaissance command", 0)
        try:
            result = await self._sessions[airframe].command_long(
                command, *params, timeout_s=timeout_s, retries=retries
            )
        except (LinkError, FrameError) as exc:
            return Outcome(False, f"command {command} not sent: {exc}", 0)
        if result.is_accepted:
            return Outcome(True, result.result_name, result.attempts)
        if result.result is None:
            detail = f"no COMMAND_ACK for command {command} after {result.attempts} attempts"
        else:
            detail = f"command {command} answered {result.result_name}"
        return Outcome(False, detail, result.attempts)

    async def upload_items(
        self, airframe: str, items: Sequence[MissionItem], *, timeout_s: float, retries: int
    ) -> Outcome:
        """Upload ``items`` (see the module docstring); ok only for MAV_MISSION_ACCEPTED."""
        if not 0 < len(items) <= _MAX_ITEMS:
            raise ValueError(f"expected 1..{_MAX_ITEMS} mission items, found {len(items)}")
        refused = sorted({item.command for item in items} - _ITEMS)
        if refused:
            log.error("mission_refused", airframe=airframe, commands=refused)
            return Outcome(False, f"mission items {refused} refused: not navigation", 0)
        session = self._sessions[airframe]
        lock = self._locks.setdefault(airframe, anyio.Lock())
        try:
            async with lock:
                return await self._upload(session, items, timeout_s, retries)
        except (LinkError, FrameError) as exc:
            return Outcome(False, f"not sent: {exc}", 0)

    async def _upload(
        self, session: AirframeSession, items: Sequence[MissionItem], timeout_s: float, retries: int
    ) -> Outcome:
        airframe = session.id
        upload = _Upload(items)
        self._uploads[airframe] = upload
        attempts = 0
        try:
            while attempts <= retries and upload.acked is None:
                attempts += 1
                await session.send(
                    session.pack("mission_count", session.config.sysid, 1, len(items), 0)
                )
                # Wait while the airframe keeps asking; a silent step is a lost frame.
                while upload.acked is None:
                    upload.moved = anyio.Event()
                    with anyio.move_on_after(timeout_s) as scope:
                        await upload.moved.wait()
                    if scope.cancelled_caught:
                        break
        finally:
            del self._uploads[airframe]
        if upload.acked is None:
            log.warning("mission_upload_timed_out", airframe=airframe, attempts=attempts)
            return Outcome(False, f"no MISSION_ACK after {attempts} attempts", attempts)
        name = _MISSION_RESULT_NAMES.get(upload.acked, str(upload.acked))
        missing = sorted(set(range(len(items))) - upload.sent)
        if upload.acked == 0 and missing:
            # An airframe that "accepts" a mission it never asked all the items of holds
            # some other mission: that is no execution of this order.
            shown = ", ".join(map(str, missing[:8])) + (", ..." if len(missing) > 8 else "")
            return Outcome(False, f"{name} without asking for items {shown}", attempts)
        return Outcome(upload.acked == 0, name, attempts)

    # -- handlers (synchronous, on ingest's path: never block, never raise) ----------------

    def _on_request(self, session: AirframeSession, _label: str, msg: MavMessage) -> None:
        upload = self._uploads.get(session.id)
        if upload is None or not _for_us(msg) or int(getattr(msg, "mission_type", 0)) != 0:
            return
        seq = int(msg.seq)
        if not 0 <= seq < len(upload.items):
            return
        item = upload.items[seq]
        frame = session.pack(
            "mission_item_int",
            session.config.sysid,
            1,
            seq,
            item.frame,
            item.command,
            0,
            1,
            *item.params,
            round(item.lat_deg * 1e7),
            round(item.lon_deg * 1e7),
            item.alt_msl_m,
            0,
        )
        upload.sent.add(seq)
        upload.moved.set()
        # On a request flood the queue is full: the airframe asks again for what it needs.
        if self._queue is not None:
            with suppress(anyio.WouldBlock, anyio.ClosedResourceError):
                self._queue.send_nowait((session, frame))

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Send the mission items the handlers queued, until cancelled."""
        send, queued = anyio.create_memory_object_stream[tuple[AirframeSession, bytes]](_QUEUE_MAX)
        self._queue = send
        with send, queued:
            task_status.started()
            async for session, frame in queued:
                try:
                    await session.send(frame)
                except (LinkError, FrameError) as exc:
                    # The airframe asks again for an item it did not get, or the upload times
                    # out.
                    log.warning("mission_item_unsent", airframe=session.id, error=str(exc))

    def _on_ack(self, session: AirframeSession, _label: str, msg: MavMessage) -> None:
        upload = self._uploads.get(session.id)
        if upload is None or not _for_us(msg) or int(getattr(msg, "mission_type", 0)) != 0:
            return
        upload.acked = int(msg.type)
        upload.moved.set()

    def _on_count(self, session: AirframeSession, _label: str, msg: MavMessage) -> None:
        down = self._downloads.get(session.id)
        if down is None or not _for_us(msg) or int(getattr(msg, "mission_type", 0)) != 0:
            return
        if down.count is None:
            down.count = max(0, min(int(msg.count), _MAX_ITEMS))
            down.moved.set()

    def _on_item(self, session: AirframeSession, _label: str, msg: MavMessage) -> None:
        down = self._downloads.get(session.id)
        if down is None or down.count is None or not _for_us(msg):
            return
        seq = int(msg.seq)
        if int(getattr(msg, "mission_type", 0)) == 0 and 0 <= seq < down.count:
            down.items[seq] = msg
            down.moved.set()

    def _on_progress(self, session: AirframeSession, _label: str, msg: MavMessage) -> None:
        what: Literal["current", "reached"] = (
            "current" if msg.get_type() == "MISSION_CURRENT" else "reached"
        )
        for listener in self._listeners:
            listener(session.id, what, int(msg.seq))

    def _on_heartbeat(self, session: AirframeSession, _label: str, msg: MavMessage) -> None:
        # A ground station or companion computer under the same sysid is no autopilot.
        if msg.autopilot != _MAV_AUTOPILOT_INVALID:
            self._heard[session.id] = (int(msg.autopilot), int(msg.type))

    def _on_home(self, session: AirframeSession, _label: str, msg: MavMessage) -> None:
        if msg.latitude or msg.longitude:
            self._homes[session.id] = (msg.latitude / 1e7, msg.longitude / 1e7)
