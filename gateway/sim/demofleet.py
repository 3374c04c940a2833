"""The demo's simulated fleet: airframes on neighbouring circles round Boden, run together.

``build_demo_fleet`` makes them (``fischer-gateway simulate`` without a scenario);
``run_fleet`` flies several ``SimulatedAirframe``s in one task group, each to its own port.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from typing import TYPE_CHECKING

import anyio
import anyio.abc

from gateway.sim.airframe import SimProfile, SimulatedAirframe
from gateway.sim.autopilot import AutopilotName
from gateway.sim.resend import ResendPolicy

if TYPE_CHECKING:
    from gateway.fleet.security.tunnel import Sealer

__all__ = ["build_demo_fleet", "run_fleet"]

_DEFAULT_RESEND = ResendPolicy()


def build_demo_fleet(
    n: int = 2,
    *,
    resend: ResendPolicy | None = _DEFAULT_RESEND,
    autopilot: AutopilotName = "ardupilot",
) -> list[SimulatedAirframe]:
    """``n`` airframes (sysids 1..n) on neighbouring circles around Boden, at different phases,
    re-sending unacknowledged detections as ``resend`` says, each playing ``autopilot``."""
    if not 1 <= n <= 255:
        raise ValueError(f"n: expected 1..255 airframes, got {n!r}")
    return [
        SimulatedAirframe(
            i + 1,
            SimProfile(
                centre_lat_deg=65.8252 + 0.01 * i,
                centre_lon_deg=21.6886 + 0.02 * i,
                detection_hz=0.2,  # a FISCHER_DETECTION every 5 s
            ),
            phase_rad=i * 2.0,
            resend=resend,
            autopilot=autopilot,
        )
        for i in range(n)
    ]


async def run_fleet(
    airframes: Sequence[SimulatedAirframe],
    host: str,
    ports: Sequence[int],
    *,
    duration_s: float | None = None,
    speed: float = 1.0,
    sealers: Sequence[Sealer | None] | None = None,
    linger_s: float = 0.0,
    task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
) -> None:
    """Run several airframes in one task group, airframe ``i`` sending to ``ports[i]``.

    ``linger_s`` is each airframe's wait for its last acknowledgements (``run_udp``).
    ``task_status.started()`` is called once every airframe's socket exists. Raises
    ``ValueError`` if ``ports`` (or ``sealers``) does not match ``airframes`` in length.
    """
    seals = list(sealers) if sealers is not None else [None] * len(airframes)
    if not len(airframes) == len(ports) == len(seals):
        raise ValueError(
            f"run_fleet: {len(airframes)} airframes but {len(ports)} ports and {len(seals)} sealers"
        )
    async with anyio.create_task_group() as tg:
        for airframe, port, sealer in zip(airframes, ports, seals, strict=True):
            await tg.start(
                partial(
                    airframe.run_udp,
                    host,
                    port,
                    duration_s=duration_s,
                    speed=speed,
                    sealer=sealer,
                    linger_s=linger_s,
                )
            )
        task_status.started()
