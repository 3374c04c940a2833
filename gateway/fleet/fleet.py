"""The airframe side of one node, built from the config and run as one: ``Fleet``.

``Fleet`` owns everything that talks MAVLink to the airframes: the security material, the
links, ingest and the airframe sessions, the hop schedules, the passthroughs, the commander
that tasks airframes for a processor, and the uplink itself (``send``). The rest of the node
gives it intents only: the commander's (upload these steps, start the mission, return to
base), and the sessions' own (acknowledge these detections, send this hop schedule) never
leave the fleet: they go out through ``send`` on the airframe's active link, in the link's
security mode. The assembly (``gateway.app``) wires a ``Fleet`` to the bus and runs it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import anyio
import anyio.abc

from gateway.clock import Clock
from gateway.config import Config
from gateway.domain.terrain import TerrainModel
from gateway.errors import FrameError, LinkError, LinkUnavailable
from gateway.events import Event
from gateway.fleet.acks import DetectionLedger
from gateway.fleet.commander import FleetCommander
from gateway.fleet.hopschedule import HopSchedules
from gateway.fleet.ingest import Ingest, LinkIntake
from gateway.fleet.links import Link, make_link
from gateway.fleet.passthrough import Passthrough
from gateway.fleet.security.keys import read_key_file
from gateway.fleet.security.material import Security
from gateway.fleet.session import AirframeSession
from gateway.ops.instruments import Instruments

__all__ = ["Fleet"]

_LINK_CHECK_INTERVAL_S = 0.25


class Fleet:
    """The config's airframes, their links and the uplink (see the module docstring).

    ``publish`` puts what the airframes report on the bus; ``ledger`` (the spool) makes
    detections durable before they are acknowledged; ``commander``: build the commander a
    tasking processor needs (``self.commander`` is None without).
    """

    def __init__(
        self,
        config: Config,
        publish: Callable[[Event], bool],
        instruments: Instruments,
        clock: Clock,
        *,
        terrain: TerrainModel | None = None,
        ledger: DetectionLedger | None = None,
        commander: bool = False,
    ) -> None:
        self._inst = instruments
        self.security = Security.from_config(config, clock)
        self.ingest = Ingest(
            config.airframes,
            publish,
            instruments,
            clock,
            opener=self.security.opener,
            verifiers=self.security.verifiers,
            terrain=terrain,
            baro_sigma_m=config.terrain.baro_sigma_m,
            ledger=ledger,
            transmit=self.send,
        )
        self.sessions: dict[str, AirframeSession] = self.ingest.sessions
        self.hops = HopSchedules(self.sessions.values(), publish, instruments, clock)
        self.commander = FleetCommander(self.sessions, self.is_linked) if commander else None
        self.links: dict[str, Link] = {}
        self._links_by_label: dict[str, Link] = {}
        self._link_security: dict[str, str] = {}
        for airframe in config.airframes:
            for link_cfg in airframe.links:
                key = str(link_cfg.uri)
                if key in self.links:
                    continue
                link = make_link(link_cfg, self.ingest.on_data, self.ingest.forget_peer)
                self.links[key] = link
                self._links_by_label[link.label] = link
                self._link_security[link.label] = link_cfg.security
                self.ingest.register_link(
                    LinkIntake(
                        link.label,
                        link_cfg.security,
                        is_stream=link_cfg.uri.scheme != "udp",
                        max_chunk_bytes=link_cfg.max_frame_bytes,
                        trust=link.trust,
                        drop=link.drop,
                    )
                )
        self.passthroughs: dict[str, Passthrough] = {}
        for airframe in config.airframes:
            if airframe.passthrough is not None:
                gcs_key = (
                    None
                    if airframe.passthrough.key_file is None
                    else read_key_file(airframe.passthrough.key_file, exact=True)
                )
                passthrough = Passthrough(
                    airframe.id,
                    airframe.sysid,
                    airframe.passthrough,
                    self.send,
                    gcs_key=gcs_key,
                    refused_metric=instruments.passthrough_refused,
                )
                self.passthroughs[airframe.id] = passthrough
                self.ingest.set_passthrough(airframe.id, passthrough.forward)

    # -- state ------------------------------------------------------------------------------

    def is_linked(self, airframe: str) -> bool:
        """True if ``airframe`` has an active link."""
        return self.ingest.active_link(airframe) is not None

    def linked_count(self) -> tuple[int, int]:
        """(airframes with an active link, airframes configured)."""
        linked = sum(1 for a in self.sessions if self.is_linked(a))
        return linked, len(self.sessions)

    def is_bound(self) -> bool:
        """True while every link is bound (listening, or connected to its device)."""
        return all(link.is_bound for link in self.links.values())

    def status(self) -> dict[str, Any]:
        """The fleet's share of /status: airframes, links, hop schedules, passthroughs and
        the system ids heard that no airframe has."""
        return {
            "airframes": self.ingest.status(),
            "links": [
                {**link.status(), "security": self._link_security[link.label]}
                for link in self.links.values()
            ],
            "hop_schedules": self.hops.status(),
            "passthroughs": [p.status() for p in self.passthroughs.values()],
            "unknown_sysids": sorted(self.ingest.unknown_sysids),
        }

    # -- running ----------------------------------------------------------------------------

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind every link and passthrough, then keep the link health, the detection
        acknowledgements and the hop schedules going until cancelled (ready once bound).

        The commander, which a processor may still use while the links close, runs apart:
        ``run_commander``.
        """
        async with anyio.create_task_group() as tg:
            for link in self.links.values():
                await tg.start(link.run)
            for passthrough in self.passthroughs.values():
                await tg.start(passthrough.run)
            tg.start_soon(self._watch_links)
            if self.ingest.acks is not None:
                tg.start_soon(self.ingest.acks.run)
            tg.start_soon(self.hops.run)
            task_status.started()

    async def run_commander(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Run the commander (it sends the mission items the airframes ask for), if any."""
        if self.commander is None:
            task_status.started()
            return
        await self.commander.run(task_status=task_status)

    async def _watch_links(self) -> None:
        while True:
            self.ingest.check_links()
            await anyio.sleep(_LINK_CHECK_INTERVAL_S)

    # -- the uplink -------------------------------------------------------------------------

    async def send(self, airframe: str, frames: bytes) -> None:
        """Send raw MAVLink ``frames`` to ``airframe`` on its active link, in the link's mode.

        Only one of the airframe's configured links is used, and on it only the peer that
        last authenticated for the airframe; a tunnel link seals, a signed link signs. With
        no such link or peer the frames are refused and counted, never sent elsewhere:
        raises ``LinkUnavailable`` (or ``FrameError`` for frames a signed link cannot sign).
        """
        refused = self._inst.uplink_refused
        label = self.ingest.active_link(airframe)
        if label is None or not self.ingest.is_configured(airframe, label):
            refused.labels(airframe, "no_link").inc()
            raise LinkUnavailable(airframe, "no link of this airframe is up")
        link = self._links_by_label[label]
        peer = self.ingest.peer_for(airframe, label)
        if peer is None and link.endpoint.mode == "listen":
            refused.labels(airframe, "no_peer").inc()
            raise LinkUnavailable(label, f"no authenticated peer of {airframe} on this link")
        security = self._link_security[label]
        try:
            if security == "tunnel":
                frames = self.security.seal(airframe, frames, stream=link.endpoint.scheme != "udp")
            elif security == "signed":
                frames = self.security.sign(airframe, frames)
        except FrameError:
            refused.labels(airframe, "unsignable").inc()
            raise
        try:
            await link.send_to(peer, frames)
        except LinkError:
            refused.labels(airframe, "send_failed").inc()
            raise
        self._inst.uplink_frames.labels(airframe, label).inc()
