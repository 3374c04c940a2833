"""The daemon: builds every component from a Config, wires them and runs them in order.

The airframe side is one ``Fleet`` (``gateway.fleet.fleet``: links, ingest, sessions, the
uplink, the commander); here it is wired to the bus, the processors, the sources and the
sinks. Start-up: sink runners, then the health endpoint, then the fleet's links; only when
every link is bound does the gateway report started (and systemd READY=1). Shutdown follows
a fixed order: stop ingest (close links), let the sinks drain what is queued within half the
deadline, then cancel and close them within the rest.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from functools import partial
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import anyio
import anyio.abc
import structlog

from gateway.c2.deliverypass import DeliveryPass
from gateway.c2.plugins import PROCESSOR_GROUP, SOURCE_GROUP, build_sink, load_component
from gateway.c2.sink import ReleasesOwnAirframes, Sink
from gateway.c2.sinkrunner import SinkRunner
from gateway.c2.source import (
    KeepsStatuses,
    LedgerAware,
    OrderStatusFeed,
    OrderStatusListener,
    OwnAirframesAware,
    Source,
)
from gateway.c2.sourcepublish import SourcePublish
from gateway.clock import Clock, utc_now
from gateway.config import Config
from gateway.domain.orderbook import KeepsOrders
from gateway.domain.terrain import DemSource, TerrainModel
from gateway.events import Event
from gateway.fleet.fleet import Fleet
from gateway.flow.bus import Bus
from gateway.flow.processor import PinsUnits
from gateway.flow.processors import ProcessorRunner
from gateway.flow.tasking import TaskingProcessor
from gateway.ops.health import HealthServer
from gateway.ops.instruments import Instruments
from gateway.ops.origins import RemoteOrigins
from gateway.ops.pluginstatus import read_status
from gateway.ops.sdnotify import SystemdNotifier
from gateway.ops.supervise import Supervised, supervise
from gateway.spool.commits import COMMIT_FAILURE_REASONS
from gateway.spool.orderbook import SpoolOrderBook
from gateway.spool.store import Spool

__all__ = ["Gateway", "utc_now"]

log = structlog.get_logger(__name__)

_SPOOL_PROBE_INTERVAL_S = 5.0


def dem_sources(config: Config) -> list[DemSource]:
    """The DEM sources of the config, in order."""
    return [DemSource(s.name, s.directory, s.kind, s.sigma_m) for s in config.terrain.sources]


def terrain_model(config: Config) -> TerrainModel | None:
    """The config's terrain model, None without sources; a failing source is disabled."""
    sources = dem_sources(config)
    return TerrainModel(sources, strict=False) if sources else None


def _version() -> str:
    try:
        return version("fischer-gateway")
    except PackageNotFoundError:
        return "unknown"


def open_spool(config: Config) -> Spool:
    """The config's spool, opened; warns when it is in memory or owes unconfigured sinks.

    Raises ``SpoolError`` when the file cannot be opened.
    """
    cfg = config.spool
    spool = Spool(
        cfg.path,
        sync=cfg.sync,
        max_bytes=cfg.max_bytes,
        warn_pct=cfg.warn_pct,
        dedup_window_s=cfg.dedup_window_s,
        dead_letters_max=cfg.dead_letters_max,
    )
    if cfg.path is None and any(True for _ in config.sinks):
        log.warning(
            "spool_in_memory",
            note="spool.path is not set: durable events waiting for a sink are lost on restart",
        )
    configured = {entry.name for entry in config.sinks}
    orphans = {s: n for s, n in spool.pending_counts().items() if s not in configured}
    if orphans:
        log.warning(
            "spool_owes_unconfigured_sinks",
            pending=orphans,
            note="kept; configure the sink again, or list them with 'fischer-gateway spool status'",
        )
    if spool.pending_counts():
        log.info("spool_resumed", path=str(cfg.path), pending=spool.pending_counts())
    return spool


class Gateway:
    """One gateway node: links → ingest → bus → sink runners, plus health."""

    def __init__(
        self,
        config: Config,
        *,
        sinks: Mapping[str, Sink] | None = None,
        clock: Clock = utc_now,
        notifier: SystemdNotifier | None = None,
        source: str = "<config>",
    ) -> None:
        self.config = config
        self.instruments = Instruments()
        self.notifier = notifier or SystemdNotifier()
        self.spool = open_spool(config)
        given = dict(sinks or {})
        self.runners: dict[str, SinkRunner] = {}
        #: One delivery pass per loop pass for every runner whose sink sends without awaiting.
        self.delivery = DeliveryPass()
        for entry in config.sinks:
            sink = given.pop(entry.name, None) or build_sink(entry.type, entry.name, entry.options)
            self.runners[entry.name] = SinkRunner(
                entry,
                sink,
                self.instruments,
                spool=self.spool,
                stale=config.spool.stale,
                delivery=self.delivery,
            )
        if given:
            raise ValueError(f"sinks given for names not in the config: {sorted(given)}")
        self.processors: dict[str, ProcessorRunner] = {}
        for processor_entry in config.processors:
            component = load_component(PROCESSOR_GROUP, processor_entry.type)
            options = component.model.model_validate(processor_entry.options)
            self.processors[processor_entry.name] = ProcessorRunner(
                processor_entry.name,
                processor_entry.type,
                component.factory(processor_entry.name, options),
                self.instruments,
                self._publish,
                queue_max=processor_entry.queue_max,
            )
        self.order_status_feed = OrderStatusFeed()
        self.bus = Bus(
            config.routes,
            self.runners,
            self.instruments,
            source=source,
            processors=[*self.processors.values(), self.order_status_feed],
            spool=self.spool,
        )
        self.instruments.sink_queue.set_function(self._queue_depths)
        self.instruments.sink_outcomes.set_function(self._sink_outcomes)
        self._instrument_spool()
        self.terrain = terrain_model(config)
        self._instrument_terrain_and_readiness()
        tasking = [
            runner.processor
            for runner in self.processors.values()
            if isinstance(runner.processor, TaskingProcessor)
        ]
        self.fleet = Fleet(
            config,
            self.bus.publish,
            self.instruments,
            clock,
            terrain=self.terrain,
            ledger=self.spool,
            commander=bool(tasking),
        )
        if self.fleet.commander is not None:
            # The one place the middle and the airframe side meet for orders: the processor
            # sees only the ``AirframeCommander`` port (``gateway.flow.tasking``).
            for processor in tasking:
                processor.attach(self.fleet.commander, self.terrain, config.terrain.baro_sigma_m)
        keeping = [
            runner.processor
            for runner in self.processors.values()
            if isinstance(runner.processor, KeepsOrders)
        ]
        #: The orders processor's order book, in the spool (None without an orders processor).
        self.order_book = SpoolOrderBook(self.spool) if keeping else None
        if self.order_book is not None:
            for keeper in keeping:
                keeper.keep_orders(self.order_book)
        pinned = frozenset(
            uid
            for runner in self.processors.values()
            if isinstance(runner.processor, PinsUnits)
            for uid in runner.processor.pinned_uids
        )
        airframe_ids = [airframe.id for airframe in config.airframes]
        own = frozenset(
            uid
            for runner in self.runners.values()
            if isinstance(runner.sink, ReleasesOwnAirframes)
            for uid in runner.sink.own_uids(airframe_ids)
        )
        self.sources: list[Source] = []
        self._source_publish: list[SourcePublish] = []
        #: Other nodes' events the sources put on the bus, per node and airframe (/status).
        self.remote = RemoteOrigins(clock=clock, own=frozenset(airframe_ids))
        remote_publish = self.remote.wrap(self.bus.publish)
        for source_entry in config.sources:
            component = load_component(SOURCE_GROUP, source_entry.type)
            options = component.model.model_validate(source_entry.options)
            publish = SourcePublish(source_entry.name, pinned, own, remote_publish)
            self._source_publish.append(publish)
            self.sources.append(component.factory(source_entry.name, options, publish, clock=clock))
        self._source_records = [Supervised(s.name) for s in self.sources]
        for built in self.sources:
            if isinstance(built, OrderStatusListener):
                self.order_status_feed.add(built)
            if isinstance(built, KeepsStatuses) and self.order_book is not None:
                built.keep_statuses(self.order_book)
            if isinstance(built, OwnAirframesAware):
                built.set_own_airframes(frozenset(airframe_ids))
            if isinstance(built, LedgerAware):
                built.set_ledger(self.spool)
        self.health: HealthServer | None = None
        if config.health.enabled:
            self.health = HealthServer(
                config.health.host,
                config.health.port,
                registry=self.instruments.registry,
                status=self.status,
                is_ready=self.is_ready,
                max_connections=config.health.max_connections,
            )
        self.health_port: int | None = None
        self._shutdown = anyio.Event()
        self.stopped = anyio.Event()
        self._started_mono = time.monotonic()
        self._links_up = False
        self.log = log.bind(node=config.gateway.node_id)

    def _publish(self, event: Event) -> bool:
        """What processors publish goes on the bus like ingest's events."""
        return self.bus.publish(event)

    def _queue_depths(self) -> list[tuple[tuple[str, ...], float]]:
        depths: list[tuple[tuple[str, ...], float]] = []
        for name, runner in self.runners.items():
            latest, durable = runner.depth
            depths += [((name, "latest"), float(latest)), ((name, "durable"), float(durable))]
        return depths

    def _sink_outcomes(self) -> list[tuple[tuple[str, ...], float]]:
        series: list[tuple[tuple[str, ...], float]] = []
        for name, runner in self.runners.items():
            for outcome, count in runner.outcome_counts().items():
                if isinstance(count, int | float):  # a third-party sink's may be anything
                    series.append(((name, outcome), float(count)))
        return series

    def _instrument_spool(self) -> None:
        inst, spool = self.instruments, self.spool
        inst.spool_bytes.set_function(lambda: [((), float(spool.size_bytes))])
        inst.spool_max_bytes.set_function(lambda: [((), float(spool.max_bytes))])
        inst.spool_pending.set_function(
            lambda: [((sink,), float(n)) for sink, n in spool.pending_counts().items()]
        )
        inst.spool_dead_letters.set_function(lambda: [((), float(spool.dead_letter_count()))])
        commits, check = spool.commits, spool.start_check
        inst.spool_commits.set_function(lambda: [((), float(commits.committed))])
        # Every reason from the start, at 0: increase() then sees the first failure too.
        inst.spool_commit_failures.set_function(
            lambda: [((r,), float(commits.failures[r])) for r in COMMIT_FAILURE_REASONS]
        )
        inst.spool_wal_lost_frames.set_function(lambda: [((), float(check.lost_frames))])
        inst.spool_wal_lost_commits.set_function(lambda: [((), float(check.lost_commits))])
        inst.spool_integrity_failures.set_function(
            lambda: [((), float(len(check.problems) if check.integrity == "corrupt" else 0))]
        )

    def _instrument_terrain_and_readiness(self) -> None:
        inst, terrain = self.instruments, self.terrain
        inst.ready.set_function(lambda: [((), float(self.is_ready()))])
        if terrain is not None:
            inst.dem_errors.set_function(lambda: [(k, float(n)) for k, n in terrain.errors.items()])
            inst.dem_source_up.set_function(
                lambda: [((s.name,), float(terrain.is_source_up(s.name))) for s in terrain.sources]
            )

    def status_line(self) -> str:
        """One line for systemd's ``STATUS=``: airframes linked, sinks healthy, DEM state."""
        linked, airframes = self.fleet.linked_count()
        unhealthy = [r.name for r in self.runners.values() if r.state != "open"]
        line = (
            f"{linked}/{airframes} airframes linked, "
            f"{len(self.runners) - len(unhealthy)}/{len(self.runners)} sinks healthy"
        )
        if unhealthy:
            line += f" (not: {', '.join(unhealthy[:3])}{', ...' if len(unhealthy) > 3 else ''})"
        if self.spool.commits.failing:
            line += "; spool writes failing"
        if self.terrain is not None:
            down = [s.name for s in self.terrain.sources if not self.terrain.is_source_up(s.name)]
            if down:
                line += f"; DEM disabled: {', '.join(down)}"
        return line

    def is_ready(self) -> bool:
        """True once every link is bound and every sink is open, while the spool commits."""
        return (
            self._links_up
            and not self.spool.commits.failing
            and self.fleet.is_bound()
            and all(runner.is_open for runner in self.runners.values())
        )

    def shutdown(self) -> None:
        """Ask the gateway to stop; ``run`` returns once it has drained and closed."""
        self._shutdown.set()

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Run until ``shutdown()``; cancellation also stops it (without the drain)."""
        try:
            await self._run(task_status)
        finally:
            self.stopped.set()

    async def _run(self, task_status: anyio.abc.TaskStatus[None]) -> None:
        deadline_s = self.config.gateway.shutdown_deadline_s
        async with anyio.create_task_group() as outer:
            for runner in self.runners.values():
                await outer.start(runner.run)
            await outer.start(self.fleet.run_commander)
            for processor in self.processors.values():
                await outer.start(processor.run)
            if self.health is not None:
                self.health_port = await outer.start(self.health.run)
            async with anyio.create_task_group() as ingest:
                await ingest.start(self.fleet.run)
                for source, record in zip(self.sources, self._source_records, strict=True):
                    # A source is a plugin: its failure (or a start that never comes) is
                    # retried with backoff and shown on /status, never the daemon's end.
                    await ingest.start(partial(supervise, source.run, record, what="source"))
                ingest.start_soon(self._probe_spool)
                self._links_up = True
                outer.start_soon(self.notifier.run_watchdog)
                self.notifier.ready(self.status_line())
                outer.start_soon(self.notifier.run_status, self.status_line)
                self.log.info(
                    "gateway_started",
                    version=_version(),
                    links=len(self.fleet.links),
                    sinks=len(self.runners),
                    health_port=self.health_port,
                )
                task_status.started()
                await self._shutdown.wait()
                self.notifier.stopping()
                self.log.info("gateway_stopping", deadline_s=deadline_s)
                ingest.cancel_scope.cancel()
            self._links_up = False
            for runner in self.runners.values():
                runner.stop()
            with anyio.move_on_after(deadline_s / 2) as drain:
                for runner in self.runners.values():
                    await runner.wait_done()
            left = {r.name: r.depth for r in self.runners.values() if any(r.depth)}
            if left and self.spool.path is not None:
                self.log.warning(
                    "shutdown_left_in_spool",
                    owed={name: durable for name, (_, durable) in left.items() if durable},
                    note="delivered after the next start",
                )
            elif drain.cancelled_caught:
                self.log.error("shutdown_drain_incomplete", undelivered=left)
            for runner in self.runners.values():
                runner.close_timeout_s = deadline_s / 2
            outer.cancel_scope.cancel()
        self.spool.close()
        self.log.info("gateway_stopped")

    async def _probe_spool(self) -> None:
        """While the spool's writes fail, try one now and then: ready again once one commits.

        Without it a node whose disk was freed would stay not ready until the next detection.
        """
        while True:
            await anyio.sleep(_SPOOL_PROBE_INTERVAL_S)
            if self.spool.commits.failing:
                self.spool.probe()

    def status(self) -> dict[str, Any]:
        """The whole node's state, for /status."""
        fleet = self.fleet.status()
        return {
            "node_id": self.config.gateway.node_id,
            "version": _version(),
            "uptime_s": round(time.monotonic() - self._started_mono, 3),
            "ready": self.is_ready(),
            "airframes": fleet["airframes"],
            "links": fleet["links"],
            "hop_schedules": fleet["hop_schedules"],
            "passthroughs": fleet["passthroughs"],
            "sources": [
                {
                    "source": s.name,
                    **(read_status(s.status, f"source {s.name}") or {}),
                    "pinned_refused": p.refused["pinned"],
                    "own_refused": p.refused["own"],
                    "extension_refused": p.refused["extension"],
                    "state": r.state,
                    "reason": r.reason,
                    "restarts": r.restarts,
                }
                for s, r, p in zip(
                    self.sources, self._source_records, self._source_publish, strict=True
                )
            ],
            "unknown_sysids": fleet["unknown_sysids"],
            "remote": self.remote.status(),
            "sinks": [runner.status() for runner in self.runners.values()],
            "spool": {
                # failing: writes do not commit now; recovered_with_loss: this start could
                # not recover everything (start_check says what), until the next restart.
                "state": (
                    "failing"
                    if self.spool.commits.failing
                    else "recovered_with_loss"
                    if self.spool.start_check.loss
                    else "ok"
                ),
                "reason": self.spool.commits.reason or self.spool.start_check.loss,
                "path": None if self.spool.path is None else str(self.spool.path),
                "size_bytes": self.spool.size_bytes,
                "max_bytes": self.spool.max_bytes,
                "pending": self.spool.pending_counts(),
                "refused": self.spool.refused,
                "dead_letters": self.spool.dead_letter_count(),
                "commits": self.spool.commits.status(),
                "start_check": self.spool.start_check.status(),
            },
            "processors": [p.status() for p in self.processors.values()],
            "listeners": [self.health.stats.status()] if self.health is not None else [],
            "terrain": [] if self.terrain is None else self.terrain.status(),
        }
