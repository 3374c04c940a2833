"""A simulated airframe that answers through MAVSDK's autopilot-side server plugins.

``MavsdkAutopilot`` runs MAVSDK (its C++ core, in this process) as an AUTOPILOT component on
its own event loop in a thread. It speaks UDP to the gateway's airframe link (unsecured:
MAVSDK knows neither the tunnel nor our keys) through a relay this peer owns, so a test can
see and steer what crosses the link:

- ``telemetry_server`` publishes a position, a home position and a battery level twice a
  second (what the gateway's acceptance checks need);
- ``mission_raw_server`` takes mission uploads (recorded in ``missions``) and, once
  ``action_server`` has been put in MISSION mode (``flight_modes``), completes one item every
  ``step_s`` so the gateway sees MISSION_CURRENT / MISSION_ITEM_REACHED to the end; the
  published position jumps to each item as it is completed (``flown``: the positions in
  order), so the gateway's completion check (last item reached *and* the airframe there)
  sees it arrive;
- the relay records the type of every message the gateway sent the airframe (``uplink``), the
  command of every command and mission item among them (``uplink_commands``), and
  drops the airframe's COMMAND_ACKs while ``drop_command_acks`` is set (``dropped_acks``).

Nothing here mirrors MAVLink's command or mission protocol: MAVSDK answers both.
"""

from __future__ import annotations

import asyncio
import contextlib
import selectors
import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mav

mavsdk = __import__("pytest").importorskip("mavsdk.asyncio")
from mavsdk.asyncio.plugins.action_server import ActionServerAsync  # noqa: E402
from mavsdk.asyncio.plugins.mission_raw_server import MissionRawServerAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry_server import TelemetryServerAsync  # noqa: E402
from mavsdk.plugins import action_server as actions  # noqa: E402
from mavsdk.plugins import telemetry_server as telemetry  # noqa: E402

__all__ = ["MavsdkAutopilot"]


@dataclass
class MavsdkAutopilot:
    """See the module docstring; ``gateway_port`` is the gateway's UDP link port."""

    gateway_port: int
    lat_deg: float = 65.83
    lon_deg: float = 21.00
    alt_msl_m: float = 500.0
    battery_pct: float = 80.0
    step_s: float = 0.3
    drop_command_acks: bool = False
    missions: list[list[tuple[int, int, float, float, float]]] = field(default_factory=list)
    flight_modes: list[str] = field(default_factory=list)
    uplink: list[str] = field(default_factory=list)
    uplink_commands: list[int] = field(default_factory=list)
    dropped_acks: int = 0
    items_completed: int = 0
    flown: list[tuple[float, float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._home = (self.lat_deg, self.lon_deg)
        self._front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._front.bind(("127.0.0.1", 0))
        self.relay_port = int(self._front.getsockname()[1])
        self._back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._back.bind(("127.0.0.1", 0))
        self._client: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._parse_up = mav.MAVLink(None)
        self._parse_down = mav.MAVLink(None)

    # -- the relay -------------------------------------------------------------------------

    def _relay(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self._front, selectors.EVENT_READ)
            selector.register(self._back, selectors.EVENT_READ)
            while not self._stop.is_set():
                for key, _ in selector.select(timeout=0.1):
                    sock = key.fileobj
                    assert isinstance(sock, socket.socket)
                    try:
                        data, sender = sock.recvfrom(65535)
                    except OSError:
                        continue
                    try:
                        if sock is self._front:  # MAVSDK → gateway
                            self._client = sender
                            if self.drop_command_acks and self._is_ack(data):
                                self.dropped_acks += 1
                                continue
                            self._back.sendto(data, ("127.0.0.1", self.gateway_port))
                        elif self._client is not None:  # gateway → MAVSDK
                            for msg in self._parse_up.parse_buffer(data) or ():
                                self.uplink.append(msg.get_type())
                                if hasattr(msg, "command"):  # commands and mission items
                                    self.uplink_commands.append(int(msg.command))
                            self._front.sendto(data, self._client)
                    except OSError:
                        continue

    def _is_ack(self, data: bytes) -> bool:
        try:
            messages = self._parse_down.parse_buffer(data) or ()
        except Exception:  # noqa: BLE001 - a frame pymavlink cannot read is not an ACK
            return False
        return any(m.get_type() == "COMMAND_ACK" for m in messages)

    # -- MAVSDK ----------------------------------------------------------------------------

    async def _main(self) -> None:
        settings = mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.AUTOPILOT)
        async with mavsdk.Mavsdk(settings) as sdk:
            await sdk.add_any_connection(f"udpout://127.0.0.1:{self.relay_port}")
            component = await sdk.server_component()
            missions = MissionRawServerAsync(component)
            action = ActionServerAsync(component)
            tel = TelemetryServerAsync(component)
            allow = actions.AllowableFlightModes(True, True, True, True, True, True, True)
            await action.set_allowable_flight_modes(allow)
            await action.set_armable(True, True)
            await action.set_armed_state(True)
            self._loop = asyncio.get_running_loop()
            self._stopping = asyncio.Event()
            self._ready.set()
            tasks = [
                asyncio.ensure_future(c)
                for c in (
                    self._publish(tel),
                    self._take_missions(missions),
                    self._take_modes(action, missions),
                )
            ]
            try:
                await self._stopping.wait()
            finally:
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)

    async def _publish(self, tel: Any) -> None:
        while True:
            where = telemetry.Position(self.lat_deg, self.lon_deg, self.alt_msl_m, 100.0)
            await tel.publish_position(
                where, telemetry.VelocityNed(0.0, 0.0, 0.0), telemetry.Heading(90.0)
            )
            await tel.publish_home(telemetry.Position(*self._home, 400.0, 0.0))
            await tel.publish_battery(telemetry.Battery(22.0, self.battery_pct))
            await asyncio.sleep(0.5)

    async def _take_missions(self, missions: Any) -> None:
        async for _result, plan in missions.subscribe_incoming_mission():
            self.missions.append(
                [(i.seq, i.command, i.x / 1e7, i.y / 1e7, i.z) for i in plan.mission_items]
            )

    async def _take_modes(self, action: Any, missions: Any) -> None:
        async for _result, mode in action.subscribe_flight_mode_change():
            self.flight_modes.append(mode.name)
            if mode.name == "MISSION" and self.missions:
                for _seq, _command, lat, lon, _alt in self.missions[-1]:
                    await asyncio.sleep(self.step_s)
                    self.lat_deg, self.lon_deg = lat, lon  # arrived: published from now on
                    self.flown.append((lat, lon))
                    await missions.set_current_item_complete()
                    self.items_completed += 1

    def _thread(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported to the test that started it
            self._error = exc
            self._ready.set()

    @contextlib.contextmanager
    def running(self) -> Iterator[MavsdkAutopilot]:
        """Relay and MAVSDK in threads for the ``with`` block."""
        relay = threading.Thread(target=self._relay, daemon=True)
        sdk = threading.Thread(target=self._thread, daemon=True)
        relay.start()
        sdk.start()
        try:
            if not self._ready.wait(30) or self._error is not None:
                raise RuntimeError(f"MAVSDK autopilot did not start: {self._error!r}")
            yield self
        finally:
            self._stop.set()
            if self._loop is not None and self._stopping is not None:
                self._loop.call_soon_threadsafe(self._stopping.set)
            sdk.join(timeout=10)
            relay.join(timeout=5)
            self._front.close()
            self._back.close()
