"""Playing a scenario to a gateway: MAVLink from each airframe, CoT from the friendly units.

Each scenario airframe is a ``SimulatedAirframe`` flying its orbit (real telemetry), or the
mission it is given, with the scenario's detections for it fed into the same MAVLink stream
as FISCHER_DETECTION frames (each look made from where the airframe is at that moment),
``time_usec`` the UTC time the observation is sent. Friendly units' reports go as CoT XML
datagrams (``sinks.cot``: what ATAK sends on its SA mesh) to the gateway's CoT source.
Sim time ``t`` is played at ``start + t / speed``. Each airframe keeps the detections it sent
until the gateway acknowledges them, re-sending as its ``ResendPolicy`` says.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from functools import partial
from itertools import count
from typing import TYPE_CHECKING, Any

import anyio
import anyio.abc
import structlog

from gateway.domain.geoid import bundled_geoid
from gateway.fleet.dialect import fischer_detection
from gateway.sim.airframe import SimulatedAirframe
from gateway.sim.resend import ResendPolicy
from gateway.sim.schedule import (
    BlueReport,
    SimDetection,
    blue_reports,
    seen_at,
    sensor_looks,
    target_tracks,
)
from sinks.cot.codec import to_xml
from sinks.cot.event import CotEvent
from sinks.cot.validate import UNKNOWN

if TYPE_CHECKING:
    from gateway.fleet.security.tunnel import Sealer
    from gateway.sim.scenario import Airframe, Scenario

__all__ = ["DetectionFeed", "PlayStats", "blue_force_cot", "play_scenario", "send_blue_forces"]

log = structlog.get_logger(__name__)

_EPS_S = 1e-9
#: FISCHER_DETECTION.frame_size is a uint8; a larger frame is sent as "unknown" (0).
_MAX_FRAME_SIZE = 255
#: A report stays current on the receivers' maps for this many report intervals.
STALE_INTERVALS = 3
#: ... and for at least this long.
MIN_STALE = timedelta(seconds=30)
_DEFAULT_RESEND = ResendPolicy()


class DetectionFeed:
    """One airframe's scenario detections as a ``MessageFeed`` of FISCHER_DETECTION messages.

    Each look is made when it falls due, from where ``where`` (sim time → lat, lon) says the
    airframe is then: on its orbit, or wherever its mission took it.
    """

    def __init__(
        self,
        scenario: Scenario,
        airframe: Airframe,
        end_s: float,
        where: Callable[[float], tuple[float, float]],
    ) -> None:
        self._scenario, self._airframe, self._where = scenario, airframe, where
        self._tracks = target_tracks(scenario)
        self._looks = sensor_looks(airframe, end_s)
        self._next = next(self._looks, None)
        self._ids = count(1)
        #: Detections handed out so far.
        self.sent = 0

    def next_due_s(self) -> float:
        """The sim time of the next look (inf when there are no more)."""
        return math.inf if self._next is None else self._next[0]

    def messages_at(self, t_s: float, unix_s: float) -> list[Any]:
        """Every detection of the looks due by ``t_s``, observed at UNIX time ``unix_s``."""
        seen: list[SimDetection] = []
        while self._next is not None and self._next[0] <= t_s + _EPS_S:
            look = self._next
            here = self._where(look[0])
            seen.extend(
                seen_at(self._scenario, self._airframe, self._tracks, look, here, self._ids)
            )
            self._next = next(self._looks, None)
        # One sensor frame per sensor (same airframe, sensor and time): each says its size.
        sizes = Counter(d.sensor_id for d in seen)
        messages = [_detection_message(d, unix_s, sizes[d.sensor_id]) for d in seen]
        self.sent += len(messages)
        return messages


def _detection_message(d: SimDetection, unix_s: float, frame_size: int) -> Any:
    return fischer_detection(
        time_usec=round(unix_s * 1e6),
        detection_id=d.detection_id,
        lat_e7=round(d.lat_deg * 1e7),
        lon_e7=round(d.lon_deg * 1e7),
        alt_msl_m=d.alt_msl_m,
        sigma_h_m=d.sigma_h_m,
        class_id=d.class_id,
        sensor=d.sensor_id,
        confidence_pct=round(d.confidence * 100),
        subtype=d.subtype,
        frame_size=frame_size if frame_size <= _MAX_FRAME_SIZE else 0,
    )


def blue_force_cot(report: BlueReport, now: datetime, stale_after: timedelta) -> bytes:
    """A friendly position report as ATAK sends it: one CoT 2.0 XML event, ``how`` m-g."""
    undulation = bundled_geoid().undulation(report.lat_deg, report.lon_deg)
    event = CotEvent(
        uid=report.uid,
        type=report.type,
        how="m-g",
        time=now,
        start=now,
        stale=now + stale_after,
        lat=report.lat_deg,
        lon=report.lon_deg,
        hae=report.alt_msl_m + undulation if undulation is not None else UNKNOWN,
        ce=10.0,
        le=15.0,
        callsign=report.callsign,
        group=("Cyan", "Team Member"),
    )
    return to_xml(event)


@dataclass(slots=True)
class PlayStats:
    """What a scenario run sent; ``airframes`` (by scenario id) are filled in as it starts."""

    frames: int = 0
    detections: int = 0
    reports: int = 0
    reports_refused: int = 0
    airframes: dict[str, SimulatedAirframe] = field(default_factory=dict)


async def send_blue_forces(
    scenario: Scenario,
    host: str,
    port: int,
    *,
    end_s: float,
    speed: float,
    stats: PlayStats,
    task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
) -> None:
    """Send every friendly report of ``scenario`` up to ``end_s`` as a CoT datagram.

    A send refused (ICMP port unreachable: nothing listens yet) is counted, not raised.
    """
    intervals = {unit.uid: unit.report_interval_s for unit in scenario.blue_forces}
    async with await anyio.create_connected_udp_socket(remote_host=host, remote_port=port) as sock:
        task_status.started()
        start = anyio.current_time()
        for report in blue_reports(scenario, end_s):
            await anyio.sleep(max(start + report.t_s / speed - anyio.current_time(), 0.0))
            stale = max(timedelta(seconds=STALE_INTERVALS * intervals[report.uid]), MIN_STALE)
            try:
                await sock.send(blue_force_cot(report, datetime.now(UTC), stale))
            except ConnectionRefusedError:
                stats.reports_refused += 1
                continue
            stats.reports += 1


async def play_scenario(
    scenario: Scenario,
    host: str,
    port: int,
    *,
    cot: tuple[str, int] | None = None,
    duration_s: float | None = None,
    speed: float = 1.0,
    sealers: Sequence[Sealer | None] | None = None,
    stats: PlayStats | None = None,
    resend: ResendPolicy | None = _DEFAULT_RESEND,
    linger_s: float = 0.0,
    task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
) -> PlayStats:
    """Play ``scenario`` to the gateway link at ``host:port`` (and its CoT source at ``cot``).

    Runs for ``duration_s`` of sim time (the scenario's own by default) and returns what was
    sent. Without ``cot`` the friendly units are not sent. ``sealers`` (one per airframe,
    in the scenario's order) seal the frames in the tunnel. ``resend`` and ``linger_s`` are
    each airframe's (``SimulatedAirframe``, ``run_udp``). ``task_status.started()`` once
    every socket exists. Raises ``ValueError`` for a bad speed or sealer count, ``OSError``
    if a socket cannot open.
    """
    if not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"speed: expected a positive finite number, got {speed!r}")
    seals = list(sealers) if sealers is not None else [None] * len(scenario.airframes)
    if len(seals) != len(scenario.airframes):
        raise ValueError(f"{len(scenario.airframes)} airframes but {len(seals)} sealers")
    end_s = scenario.duration_s if duration_s is None else duration_s
    stats = stats if stats is not None else PlayStats()
    flyers: list[SimulatedAirframe] = []
    feeds: list[DetectionFeed] = []
    for a in scenario.airframes:
        flyer = SimulatedAirframe(
            a.sysid,
            a.profile(),
            phase_rad=math.radians(a.orbit.phase_deg),
            resend=resend,
            autopilot=a.autopilot,
        )
        feed = DetectionFeed(scenario, a, end_s, flyer.position_at)
        flyer.feed = feed
        flyers.append(flyer)
        feeds.append(feed)
    stats.airframes = {a.id: flyer for a, flyer in zip(scenario.airframes, flyers, strict=True)}
    async with anyio.create_task_group() as tg:
        for flyer, sealer in zip(flyers, seals, strict=True):
            await tg.start(
                partial(
                    flyer.run_udp,
                    host,
                    port,
                    duration_s=end_s,
                    speed=speed,
                    sealer=sealer,
                    linger_s=linger_s,
                )
            )
        if cot is not None and scenario.blue_forces:
            await tg.start(
                partial(send_blue_forces, scenario, *cot, end_s=end_s, speed=speed, stats=stats)
            )
        task_status.started()
    stats.frames = sum(flyer.frames_sent for flyer in flyers)
    stats.detections = sum(feed.sent for feed in feeds)
    return stats
