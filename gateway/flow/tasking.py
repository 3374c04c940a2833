"""The airframe commander: the port through which the middle tasks the airframe side.

The orders processor decides *what* an airframe is told, as intents: upload these mission
steps, start the mission, return to base. The airframe side (``gateway.fleet.commander``)
knows *how* MAVLink carries them: the mission items, and the commands or autopilot modes
(``ModeCommands``: PX4 or plain MAVLink). The two sides never import each other: this
Protocol is the contract; the fleet (``gateway.fleet.fleet``) builds the implementation and
``gateway.app`` hands it to every processor that asks for one (``TaskingProcessor``). Its
values (``MissionStep``, ``ModeCommands``, ``Outcome``) live in ``gateway.domain.mission``,
below both.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Literal, Protocol, runtime_checkable

from gateway.domain.mission import MissionStep, ModeCommands, Outcome
from gateway.domain.terrain import TerrainModel

__all__ = ["AirframeCommander", "MissionListener", "TaskingProcessor"]

MissionListener = Callable[[str, Literal["current", "reached"], int], None]
"""Told (airframe, "current" or "reached", item seq) from MISSION_CURRENT / ITEM_REACHED."""


@runtime_checkable
class AirframeCommander(Protocol):
    """Sends tasking to the fleet's airframes over their sessions (see the module docstring)."""

    def is_known(self, airframe: str) -> bool:
        """True if ``airframe`` is configured."""
        ...

    def is_linked(self, airframe: str) -> bool:
        """True if ``airframe`` has an active link with a peer to send to."""
        ...

    def home(self, airframe: str) -> tuple[float, float] | None:
        """The airframe's home (lat, lon) from its HOME_POSITION, if it has reported one."""
        ...

    async def upload_mission(
        self, airframe: str, steps: Sequence[MissionStep], *, timeout_s: float, retries: int
    ) -> Outcome:
        """Upload ``steps`` as the airframe's mission; ``ok`` only once the airframe accepted
        it, having asked for every step (``timeout_s`` per step, ``retries`` restarts)."""
        ...

    async def download_mission(
        self, airframe: str, *, timeout_s: float, retries: int
    ) -> tuple[Outcome, tuple[MissionStep, ...]]:
        """Read the airframe's mission back (MISSION_REQUEST_LIST, then each item); ``ok``
        with its steps, or not ok saying why (an item that is no waypoint or timed loiter
        is no mission of ours: not ok, naming it)."""
        ...

    async def start_mission(
        self,
        airframe: str,
        items: int,
        mode_commands: ModeCommands,
        *,
        timeout_s: float,
        retries: int,
    ) -> Outcome:
        """Start the uploaded mission of ``items`` steps; ``ok`` only once the airframe
        accepted the command (``timeout_s`` per attempt, ``retries`` resends)."""
        ...

    async def return_to_base(
        self, airframe: str, mode_commands: ModeCommands, *, timeout_s: float, retries: int
    ) -> Outcome:
        """Send the airframe home; ``ok`` only once it accepted the command."""
        ...

    def on_mission(self, listener: MissionListener) -> None:
        """Tell ``listener`` about mission progress of every airframe from now on."""
        ...


@runtime_checkable
class TaskingProcessor(Protocol):
    """A processor that commands airframes: the assembly attaches the commander before run."""

    def attach(
        self, commander: AirframeCommander, terrain: TerrainModel | None, baro_sigma_m: float
    ) -> None:
        """Take the commander and the node's terrain model (None without DEM sources)."""
        ...
