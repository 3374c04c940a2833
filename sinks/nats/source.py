"""The ``nats`` source: other nodes' detections and airframe states onto this node's bus.

An aggregating node's ``FSG_<node>_PIC`` stream sources every remote node's detections
and newest airframe states over the leaf link (``sinks.nats.streams``). One durable pull
consumer per source reads it: each message is checked (``sinks.nats.subjects``: the subject
names a configured remote, the body is a valid event of the kind and airframe it names),
marked with its node of origin (``origin_node``) and published on the bus; another node's
state of an airframe of this node's own fleet is refused (``set_own_airframes``). It is
acknowledged only once the spool's group commit holding it has committed (``set_ledger``);
a message the spool refused, or whose group did not commit, is asked again for later. A
detection whose event id was already taken is acknowledged and dropped: JetStream
de-duplicates only inside its window, the consumer side by id (the spool's ids, kept across
restarts for its ``dedup_window_s``, and the newest ``remember_ids`` in memory).
A remote stream not heard from for ``nudge_s`` is nudged (its source taken out of the
aggregate stream and put back): newer servers otherwise back off retrying a failed source
for up to two minutes after the link is back. The ``nats`` sink never publishes an event
with an ``origin_node``, so nothing loops.

The source never ends on a NATS failure: it reconnects with a growing pause and shows the
reason on ``/status``. Bad messages are counted by reason and acknowledged (never
redelivered), logged at most every 10 s.
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections import Counter, OrderedDict
from collections.abc import Callable

import anyio
import anyio.abc
import structlog
from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.js import JetStreamContext
from nats.js.api import AckPolicy, ConsumerConfig, DeliverPolicy
from nats.js.errors import NotFoundError
from pydantic import Field, ValidationInfo, field_validator

from gateway.c2.source import Commit, DetectionLedger, SourceConfig
from gateway.clock import Clock
from gateway.events import Event, Telemetry
from gateway.ops.logsetup import RateLimit
from sinks.nats.connection import NatsServer, connect
from sinks.nats.pull import Puller
from sinks.nats.streams import aggregate_stream, ensure_stream
from sinks.nats.subjects import NODE_PATTERN, BadMessage, Carried, decode_event

__all__ = ["NatsSource", "NatsSourceConfig"]

log = structlog.get_logger(__name__)

_RETRY_MAX_S = 10.0
#: A spool group commits at the end of its loop pass; one not settled by then is a failure.
_COMMIT_WAIT_S = 30.0


class NatsSourceConfig(SourceConfig, NatsServer):
    """Options of the ``nats`` source: this node's server and the nodes it aggregates."""

    remotes: list[str] = Field(
        min_length=1,
        max_length=64,
        description="The nodes whose events this node takes (each a JetStream domain "
        "reachable over the leaf link).",
    )
    durable: str | None = Field(
        default=None,
        pattern=r"^[A-Za-z0-9_-]{1,64}$",
        description="Durable consumer name; defaults to fsg-<source name>.",
    )
    create_streams: bool = Field(
        default=True,
        description="Create the aggregate stream if missing; false: only check the one ops made.",
    )
    batch: int = Field(default=256, ge=1, le=4096, description="Messages fetched at once.")
    ack_wait_s: float = Field(
        default=30.0, ge=1, le=3600, description="Redelivery after this long unacknowledged."
    )
    max_age_h: float = Field(default=72.0, gt=0, le=24 * 365, description="Kept in the stream.")
    max_bytes: int = Field(default=1 << 30, ge=1 << 20, description="Aggregate stream size cap.")
    duplicate_window_s: float = Field(
        default=600.0, ge=10, le=86_400, description="De-duplication window of the stream."
    )
    nudge_s: float = Field(
        default=3.0,
        ge=0.5,
        le=600,
        description="A remote stream not heard from (or in error) for this long is nudged: "
        "the aggregate stream's config re-applied, at most once per this interval.",
    )
    remember_ids: int = Field(
        default=200_000,
        ge=1000,
        le=5_000_000,
        description="Detection ids remembered to drop a repeat beyond the window.",
    )

    @field_validator("remotes")
    @classmethod
    def _nodes(cls, remotes: list[str], info: ValidationInfo) -> list[str]:
        import re

        for node in remotes:
            if not re.fullmatch(NODE_PATTERN, node):
                raise ValueError(f"{node[:64]!r}: a node name is 1-32 letters, digits, '_' or '-'")
        if len(set(remotes)) != len(remotes):
            raise ValueError("a node is named twice")
        if info.data.get("node") in remotes:
            raise ValueError(f"{info.data['node']!r} is this node itself")
        return remotes


class NatsSource:
    """A durable pull consumer of the aggregate stream feeding the local bus."""

    config_model = NatsSourceConfig

    def __init__(
        self,
        name: str,
        config: NatsSourceConfig,
        publish: Callable[[Event], bool],
        *,
        clock: Clock,
    ) -> None:
        if config.node in config.remotes:
            raise ValueError(f"remotes: {config.node!r} is this node itself")
        self.name = name
        self.config = config
        self._publish = publish
        self._clock = clock
        self._counts: Counter[str] = Counter()
        self._by_node: Counter[str] = Counter()
        self._seen: OrderedDict[str, None] = OrderedDict()
        self._connected = self._was_connected = False
        self._stale: list[str] = []
        self._reason: str | None = None
        self._log_limit = RateLimit(interval_s=10.0)
        self._remotes = frozenset(config.remotes)
        self._own: frozenset[str] = frozenset()
        self._ledger: DetectionLedger | None = None

    def set_own_airframes(self, airframes: frozenset[str]) -> None:
        """This node's own airframe ids: another node's state of one is refused."""
        self._own = frozenset(airframes)

    def set_ledger(self, ledger: DetectionLedger) -> None:
        """The spool: detection ids taken across restarts, and its group commit to ack after."""
        self._ledger = ledger

    def status(self) -> dict[str, object]:
        """Connection, the last failure, counts by outcome and events taken per node."""
        return {
            "node": self.config.node,
            "remotes": list(self.config.remotes),
            "connected": self._connected,
            "reason": self._reason,
            "stale_sources": list(self._stale),
            "counts": dict(self._counts),
            "by_node": dict(self._by_node),
        }

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Report started at once, then consume until cancelled, reconnecting as needed."""
        task_status.started()
        pause = 0.2
        while True:
            self._was_connected = False
            try:
                await self._consume()
            except Exception as exc:  # noqa: BLE001 - any NATS failure: retried, shown on /status
                self._connected = False
                while isinstance(exc, ExceptionGroup) and len(exc.exceptions) == 1:
                    exc = exc.exceptions[0]  # the task group's one failure, not its wrapper
                self._reason = f"{type(exc).__name__}: {str(exc)[:200]}"
                self._counts["reconnects"] += 1
                if self._log_limit.allow("failed"):
                    log.warning("nats_source_retry", source=self.name, reason=self._reason)
            if self._was_connected:
                pause = 0.2  # it worked for a while: the next failure starts short again
            await anyio.sleep(pause)
            pause = min(pause * 2, _RETRY_MAX_S)

    async def _consume(self) -> None:
        cfg = self.config
        nc = await connect(cfg, self.name)
        try:
            js = nc.jetstream(timeout=cfg.request_timeout_s)
            wanted = aggregate_stream(
                cfg.node,
                cfg.remotes,
                cfg.max_age_h * 3600.0,
                cfg.max_bytes,
                cfg.duplicate_window_s,
            )
            await ensure_stream(js, wanted, create=cfg.create_streams)
            durable = cfg.durable or f"fsg-{self.name}"
            stream = wanted.name or ""
            await _ensure_consumer(js, stream, durable, cfg)
            puller = Puller(nc, stream, durable, batch=cfg.batch)
            self._connected = self._was_connected = True
            self._reason = None
            async with anyio.create_task_group() as tasks:
                tasks.start_soon(self._watch, js, stream)
                tasks.start_soon(puller.run)
                while True:
                    await self._take(await puller.next_batch())
        finally:
            self._connected = False
            await _close(nc)

    async def _watch(self, js: JetStreamContext, stream: str) -> None:
        """Nudge the aggregate stream when a remote source is stale.

        Newer servers back off retrying a source (up to minutes) after it failed: a remote
        stream not there yet, a leaf link cut. Taking the stale sources out and putting them
        back restarts sourcing at once, so a link that is back is caught up in about a
        second; while the link is still down a nudge costs two local API calls.
        """
        stale_ns = self.config.nudge_s * 1e9
        last = -self.config.nudge_s
        while True:
            await anyio.sleep(min(1.0, self.config.nudge_s))
            try:
                last = await self._check_sources(js, stream, stale_ns, last)
            except Exception as exc:  # noqa: BLE001 - a slow API call: try again next time
                if self._log_limit.allow("watch"):
                    log.info("nats_source_watch_failed", source=self.name, error=str(exc)[:200])

    async def _check_sources(
        self, js: JetStreamContext, stream: str, stale_ns: float, last: float
    ) -> float:
        """Nudge the stale sources unless nudged within ``nudge_s``; the last nudge's time."""
        info = await js.stream_info(stream)
        stale = sorted(
            source.name
            for source in info.sources or []
            if source.error is not None
            or source.active is None
            or not 0 <= source.active <= stale_ns
        )
        self._stale = stale
        now = anyio.current_time()
        if stale and now - last >= self.config.nudge_s:
            last = now
            # Re-applying the same config changes nothing on 2.11+ (measured): the stale
            # sources are taken out and put back, which restarts them where they were
            # (the stream remembers each source's last sequence; nothing is re-copied).
            config = info.config
            kept = [source for source in config.sources or [] if source.name not in stale]
            await js.update_stream(dataclasses.replace(config, sources=kept))
            await js.update_stream(config)
            self._counts["nudges"] += 1
        return last

    async def _take(self, messages: list[Msg]) -> None:
        """Publish a batch's events, then ack each once the spool group holding it committed.

        A bad message, another node's event about one of our airframes and a detection taken
        already are acked at once. When the bus refuses one (a full spool), it and the rest
        of the batch are asked again in a second, in order (not after ack_wait); when the
        group does not commit, what it held is asked again too.
        """
        done: list[Msg] = []
        held: list[tuple[Msg, Carried]] = []
        later: list[Msg] = []
        group: Commit | None = None
        ids: set[str] = set()  # this batch's kept ids: a repeat inside it is a duplicate
        for index, message in enumerate(messages):
            event = self._check(message, ids)
            if event is None:
                done.append(message)
                continue
            if group is None and self._ledger is not None:
                group = self._ledger.group()
            if not self._publish(event):
                self._counts["refused"] += 1
                later = messages[index:]
                break
            if not isinstance(event, Telemetry):
                ids.add(event.event_id)
                if self._ledger is not None:
                    self._ledger.remember(event.event_id)
            held.append((message, event))
        committed = await self._committed(group)
        for message in done:
            await message.ack()
        for message, event in held:
            if not committed:
                await message.nak(delay=1.0)
                continue
            if not isinstance(event, Telemetry):
                self._remember(event.event_id)
            self._counts[event.kind.value] += 1
            self._by_node[event.origin_node or ""] += 1
            await message.ack()
        if held and not committed:
            self._counts["not_committed"] += len(held)
            if self._log_limit.allow("commit"):
                log.error("nats_batch_not_committed", source=self.name, count=len(held))
        for message in later:
            await message.nak(delay=1.0)

    def _check(self, message: Msg, batch_ids: set[str]) -> Carried | None:
        """The event to publish, or None (counted) for one to ack and drop."""
        try:
            event = decode_event(message.subject, message.data)
            if event.origin_node not in self._remotes:
                raise BadMessage(f"subject {message.subject[:120]!r}: not a configured remote")
        except BadMessage as exc:
            self._counts["bad"] += 1
            if self._log_limit.allow("bad"):
                log.warning("nats_message_refused", source=self.name, reason=str(exc))
            return None
        if isinstance(event, Telemetry) and event.airframe in self._own:
            # Another node (or whoever can publish on its subjects) reporting the state of
            # one of this node's own airframes: it would move that airframe on the map and in
            # the archive (sinks key an airframe by its id). Its state comes from its own
            # links only: refused for good, never retried. (A detection of it is taken,
            # once: one this node took in itself has the same id, which the spool holds.)
            self._counts["own_airframe"] += 1
            if self._log_limit.allow("own_airframe"):
                log.warning(
                    "nats_own_airframe_refused",
                    source=self.name,
                    node=event.origin_node,
                    airframe=event.airframe[:64],
                    refused=self._counts["own_airframe"],
                )
            return None
        if not isinstance(event, Telemetry) and (
            event.event_id in self._seen
            or event.event_id in batch_ids
            or (self._ledger is not None and self._ledger.seen(event.event_id))
        ):
            self._counts["duplicate"] += 1
            return None
        return event

    async def _committed(self, group: Commit | None) -> bool:
        """Whether ``group`` committed (True without one: nothing to wait for)."""
        if group is None or self._ledger is None:
            return True
        settled = anyio.Event()
        outcome: list[bool] = []

        def done(committed: bool) -> None:
            outcome.append(committed)
            settled.set()

        group.when_done(done)
        if not group.scheduled:
            self._ledger.flush()  # no loop pass to end it: now
        with anyio.move_on_after(_COMMIT_WAIT_S):
            await settled.wait()
        return outcome == [True]

    def _remember(self, event_id: str) -> None:
        self._seen[event_id] = None
        if len(self._seen) > self.config.remember_ids:
            self._seen.popitem(last=False)


async def _ensure_consumer(
    js: JetStreamContext, stream: str, durable: str, cfg: NatsSourceConfig
) -> None:
    """The durable pull consumer of ``stream``: created if missing, its position kept."""
    try:
        await js.consumer_info(stream, durable)
    except NotFoundError:
        await js.add_consumer(
            stream,
            config=ConsumerConfig(
                durable_name=durable,
                ack_policy=AckPolicy.EXPLICIT,
                deliver_policy=DeliverPolicy.ALL,
                ack_wait=cfg.ack_wait_s,
                max_ack_pending=max(cfg.batch * 4, 1024),
                max_waiting=16,
            ),
        )


async def _close(nc: Client) -> None:
    with anyio.CancelScope(shield=True):
        try:
            await asyncio.wait_for(nc.close(), timeout=2.0)
        except Exception as exc:  # noqa: BLE001 - closing: nothing left to do but log it
            log.debug("nats_close_failed", error=str(exc)[:200])
