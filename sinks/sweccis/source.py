"""The SWECCIS order source: five-line reconnaissance orders from a SWECCIS server.

Connects as the ``sweccis`` sink does (``sinks.sweccis.link``: TLS 1.2+, client
certificate, pinned CA, 4-byte length frames), registers to receive the **Orders** FAS, and
reads the orders the server sends. Each valid ``Orders`` document is published as a
``FiveLineOrder`` (``event_id`` ``sweccis-order-<OrderId>``, ``source`` this source's name)
and acknowledged ``accepted`` only once ``publish`` returns True (the event is held
durably); otherwise it is not acknowledged, so the server sends it again. An order already
accepted on this run is acknowledged ``duplicate`` and not published again; one under a taken
OrderId with other content (``FiveLineOrder.content_digest``) is acknowledged ``rejected`` and
answered with an OrderStatus ``conflict``, the first order standing. An order that
fails its checks is acknowledged ``rejected`` with the reason naming the element. Taking an
order in does not execute it: that is the orders processor's, later.

With ``report_statuses`` (the default) the source also registers to publish Orders and
sends the orders processor's answer to each of its orders as an ``OrderStatus`` document
(``accepted``, ``rejected`` with the check and its numbers, ``executing``, ``completed``,
``failed``; ``on_order_status``). A status waits, in memory, until the server acknowledges
it (any ack: ``rejected`` too is final); on a new connection every status not acknowledged
yet is sent again (the server answers ``duplicate`` for what it had). At most
``max_pending_statuses`` wait; the oldest go first, counted ``status_dropped``.

Nothing the server sends ends the source: bad documents are counted (``counts``) and logged
at most once per ``LOG_INTERVAL_S`` per outcome, without their content; a frame over the
bound or a lost connection ends the connection, and the source connects again after a
jittered backoff that doubles up to ``reconnect_max_s`` and starts over once a connection
has lasted ``STABLE_S``.
"""

from __future__ import annotations

import random
import ssl
from collections import Counter, OrderedDict
from collections.abc import Callable
from datetime import datetime
from typing import ClassVar, Literal

import anyio
import anyio.abc
import anyio.to_thread
import structlog
from pydantic import Field

from gateway.c2.source import SourceConfig
from gateway.clock import utc_now
from gateway.errors import FrameError, LinkError, LinkUnavailable
from gateway.events import Event, FiveLineOrder, OrderState, OrderStatus
from gateway.ops.logsetup import RateLimit
from gateway.transports.tls import tls_context
from sinks.sweccis.fas import (
    Ack,
    AckStatus,
    DocumentError,
    Fas,
    OrderDocument,
    encode_ack,
    encode_order_status,
    parse_document,
)
from sinks.sweccis.link import SweccisLink, SweccisLinkOptions, tls_problem

__all__ = [
    "LOG_INTERVAL_S",
    "REMEMBERED_ORDERS",
    "STABLE_S",
    "SweccisSource",
    "SweccisSourceConfig",
]

log = structlog.get_logger(__name__)

#: At most one log record per outcome per this many seconds (every one is counted).
LOG_INTERVAL_S = 10.0
#: A connection that lasted this long resets the reconnect backoff.
STABLE_S = 30.0
#: Documents acknowledged on this run whose repeats are answered ``duplicate``.
REMEMBERED_ORDERS = 4096


class SweccisSourceConfig(SourceConfig, SweccisLinkOptions):
    """A SWECCIS order intake: the server, the TLS material and the reconnect backoff."""

    type: Literal["sweccis"] = Field(default="sweccis", description="The source type.")
    name: str = Field(
        default="sweccis",
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$",
        description="Named in metrics, /status and each order's source.",
    )
    reconnect_initial_s: float = Field(
        default=1.0, gt=0, le=60, description="First wait before connecting again."
    )
    reconnect_max_s: float = Field(
        default=60.0, gt=0, le=3600, description="Longest wait between connection attempts."
    )
    report_statuses: bool = Field(
        default=True,
        description="Register to publish Orders and send each order's OrderStatus documents.",
    )
    max_pending_statuses: int = Field(
        default=1000, ge=1, le=100_000, description="Order statuses waiting for the server's ack."
    )


class SweccisSource:
    """Receives five-line orders from one SWECCIS server and publishes them."""

    config_model: ClassVar[type[SweccisSourceConfig]] = SweccisSourceConfig

    def __init__(
        self,
        name: str,
        config: SweccisSourceConfig,
        publish: Callable[[Event], bool],
        *,
        clock: Callable[[], datetime] = utc_now,
    ) -> None:
        # Read the TLS files now: a missing CA or a wrong password is a config error on this
        # source's line (check-config and run build every source), not a reconnect loop.
        problem = tls_problem(config.tls_files)
        if problem is not None:
            raise ValueError(problem)
        self.name = name
        self.config = config
        self._publish = publish
        self._clock = clock
        self._context: ssl.SSLContext | None = None
        #: Document ids (None) and ``order:<OrderId>`` keys (the order's content digest) taken.
        self._acknowledged: OrderedDict[str, str | None] = OrderedDict()
        #: Orders by outcome: ``accepted``, ``duplicate``, ``rejected`` (failed a check),
        #: ``not_held`` (publish refused it: not acknowledged); frames that were no order:
        #: ``invalid`` (no readable id), ``oversize``, ``truncated``, ``unexpected``.
        self.counts: Counter[str] = Counter()
        #: Connection outcomes: ``registered``, ``failed``, ``lost``.
        self.connections: Counter[str] = Counter()
        self.state: Literal["connecting", "connected", "waiting"] = "connecting"
        self.last_error = ""
        self._log_limit = RateLimit(interval_s=LOG_INTERVAL_S)
        self._received_log = RateLimit(interval_s=1.0)
        #: Statuses of our orders not acknowledged yet, by document id, oldest first.
        self._statuses: OrderedDict[str, OrderStatus] = OrderedDict()
        self._status_ready = anyio.Event()
        self._send_lock = anyio.Lock()
        self.log = log.bind(source=name, uri=config.uri)

    def on_order_status(self, status: OrderStatus) -> None:
        """Queue a status of one of this source's orders for the server; never blocks."""
        if status.source != self.name or not self.config.report_statuses:
            return
        if len(self._statuses) >= self.config.max_pending_statuses:
            self._statuses.popitem(last=False)
            self._count("status_dropped", order_id=status.order_id)
        self._statuses[status.event_id] = status
        self._status_ready.set()

    def status(self) -> dict[str, object]:
        """What /status shows for this source."""
        return {
            "source": self.name,
            "type": "sweccis",
            "uri": self.config.uri,
            "state": self.state,
            "counts": dict(self.counts),
            "connections": dict(self.connections),
            "last_error": self.last_error,
        }

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Report started, then connect, receive and reconnect until cancelled."""
        task_status.started()  # a client binds nothing; the server may come later
        delay = self.config.reconnect_initial_s
        while True:
            self.state = "connecting"
            started = anyio.current_time()
            try:
                await self._connect_and_serve()
            except (LinkError, FrameError, TimeoutError) as exc:
                self._failed(exc)
            if anyio.current_time() - started >= STABLE_S:
                delay = self.config.reconnect_initial_s
            self.state = "waiting"
            await anyio.sleep(delay * random.uniform(0.5, 1.0))  # noqa: S311 - jitter
            delay = min(delay * 2, self.config.reconnect_max_s)

    def _failed(self, exc: Exception) -> None:
        if isinstance(exc, TimeoutError):
            reason = (
                f"{self.config.uri}: an acknowledgement not sent within {self.config.timeout_s} s"
            )
        else:
            reason = str(exc)
        if isinstance(exc, FrameError):
            self.counts["oversize" if exc.reason == "oversize" else "truncated"] += 1
        self.last_error = reason
        if self.state == "connected":
            self.connections["lost"] += 1
            if self._log_limit.allow("lost"):
                self.log.warning("sweccis_connection_lost", reason=reason)
        else:
            self.connections["failed"] += 1
            if self._log_limit.allow("failed"):
                self.log.warning("sweccis_connection_failed", reason=reason)

    async def _connect_and_serve(self) -> None:
        if self._context is None:
            try:
                self._context = await anyio.to_thread.run_sync(tls_context, self.config.tls_files)
            except (OSError, ValueError) as exc:  # the files changed since the config was checked
                raise LinkUnavailable(
                    self.config.uri, f"TLS material unusable: {exc}", what=""
                ) from exc
        publish = [Fas.ORDERS] if self.config.report_statuses else []
        link = await SweccisLink.connect(
            self.config, self._context, publish=publish, subscribe=[Fas.ORDERS]
        )
        try:
            self.state = "connected"
            self.connections["registered"] += 1
            self.log.info("sweccis_orders_registered")
            try:
                async with anyio.create_task_group() as tg:
                    if self.config.report_statuses:
                        tg.start_soon(self._send_statuses, link)
                    while True:
                        # No deadline: orders come when they come. A server that vanished is
                        # found by TCP keep-alive (gateway.transports.frames), and ends this
                        # with LinkClosed.
                        await self.handle(link, await link.receive())
            except ExceptionGroup as group:
                # One connection's failure (either task's) is what run() retries, unwrapped.
                inner = group.exceptions[0]
                if isinstance(inner, LinkError | FrameError | TimeoutError):
                    raise inner from None
                raise
        finally:
            with anyio.CancelScope(shield=True):
                await link.aclose()

    async def handle(self, link: SweccisLink, data: bytes) -> None:
        """Publish and acknowledge one frame's order, or count why not. Never raises on input."""
        try:
            document = parse_document(data, source=self.name, max_bytes=self.config.max_frame_bytes)
        except DocumentError as exc:
            if exc.doc_id is None:
                self._count("invalid", element=exc.element)
                return
            self._count("rejected", doc_id=exc.doc_id, reason=str(exc))
            await self._ack(link, exc.doc_id, "rejected", str(exc))
            return
        if isinstance(document, Ack):
            sent = self._statuses.pop(document.ref, None)
            if sent is None:
                self._count("unexpected", document="Ack")
            else:
                self.counts[f"status_{document.status}"] += 1
            return
        if not isinstance(document, OrderDocument):
            self._count("unexpected", document=type(document).__name__)
            return
        order_key = "order:" + document.order.order_id
        digest = document.order.content_digest()
        taken = self._acknowledged.get(order_key)
        if taken is not None and taken != digest:
            await self._conflict(link, document.doc_id, document.order, digest)
            return
        if document.doc_id in self._acknowledged or order_key in self._acknowledged:
            # The same document again, or the same order under another document id.
            self.counts["duplicate"] += 1
            await self._ack(link, document.doc_id, "duplicate")
            return
        if not self._publish(document.order):
            # Not held: no ack, so the server keeps the order and sends it again.
            self._count("not_held", order_id=document.order.order_id)
            return
        self.counts["accepted"] += 1
        self._acknowledged[document.doc_id] = None
        self._acknowledged[order_key] = digest
        while len(self._acknowledged) > REMEMBERED_ORDERS:
            self._acknowledged.popitem(last=False)
        if self._received_log.allow("received"):  # a flood of orders: one line a second
            self.log.info(
                "sweccis_order_received",
                received_total=self.counts["accepted"],
                order_id=document.order.order_id,
                task=document.order.task.value,
                priority=document.order.priority.value,
            )
        await self._ack(link, document.doc_id, "accepted")

    async def _conflict(
        self, link: SweccisLink, doc_id: str, order: FiveLineOrder, digest: str
    ) -> None:
        """A changed order under a taken OrderId: rejected, and an OrderStatus ``conflict``."""
        self._count("conflict", order_id=order.order_id)
        reason = (
            f"order_id: {order.order_id} was already taken with other content; the first"
            " stands: give a changed order a new id"
        )
        await self._ack(link, doc_id, "rejected", reason)
        self.on_order_status(
            OrderStatus(
                event_id=f"{order.event_id}-conflict-{digest[:12]}",
                order_event_id=order.event_id,
                order_id=order.order_id,
                source=self.name,
                airframe=order.airframe,
                time=self._clock(),
                status=OrderState.CONFLICT,
                check="order_id",
                reason=reason,
            )
        )

    async def _ack(
        self, link: SweccisLink, doc_id: str, status: AckStatus, reason: str | None = None
    ) -> None:
        await self._send(
            link, encode_ack(doc_id, status, reason, version=str(self.config.fas_version))
        )

    async def _send(self, link: SweccisLink, payload: bytes) -> None:
        # Acks and statuses come from two tasks: one frame at a time on the stream.
        with anyio.fail_after(self.config.timeout_s):
            async with self._send_lock:
                await link.send(payload)

    async def _send_statuses(self, link: SweccisLink) -> None:
        """Send every status not acknowledged yet, then each new one, on this connection."""
        sent: set[str] = set()
        while True:
            self._status_ready = anyio.Event()
            for doc_id, status in list(self._statuses.items()):
                if doc_id in sent:
                    continue
                try:
                    payload = encode_order_status(status, version=str(self.config.fas_version))
                except ValueError as exc:
                    self._statuses.pop(doc_id, None)
                    self._count("status_unencodable", order_id=status.order_id, reason=str(exc))
                    continue
                await self._send(link, payload)
                sent.add(doc_id)
            sent &= set(self._statuses)
            await self._status_ready.wait()

    def _count(self, outcome: str, **fields: object) -> None:
        self.counts[outcome] += 1
        if self._log_limit.allow(outcome):
            self.log.warning(
                "sweccis_order_refused", outcome=outcome, count=self.counts[outcome], **fields
            )
