"""The airframe commander: the port through which the middle tasks the airframe side.

The orders processor decides *what* an airframe is told (checks, mission items, commands);
the airframe side (``gateway.fleet.commander``) knows *how* MAVLink carries it. The two sides
never import each other: this Protocol is the contract, ``gateway.app`` builds the fleet's
implementation and hands it to every processor that asks for one (``TaskingProcessor``).
Its values (``MissionItem``, ``Outcome``) live in ``gateway.domain.mission``, below both.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Literal, Protocol, runtime_checkable

from gateway.domain.mission import MissionItem, Outcome
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

    async def command(
        self,
        airframe: str,
        command: int,
        params: Sequence[float],
        *,
        timeout_s: float,
        retries: int,
    ) -> Outcome:
        """COMMAND_LONG ``command`` until its COMMAND_ACK; ``ok`` only for ACCEPTED."""
        ...

    async def upload_mission(
        self, airframe: str, items: Sequence[MissionItem], *, timeout_s: float, retries: int
    ) -> Outcome:
        """Upload ``items`` as the airframe's mission; ``ok`` only for MISSION_ACK ACCEPTED."""
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
