"""The SLB order source: reconnaissance orders polled from SLB become FiveLineOrder events.

Every ``poll_interval_s`` it asks ``GET {base_url}/orders?limit=<max_orders>`` over the same
TLS as the SLB sink (client certificate, pinned CA, no proxies, no redirects, a deadline per
request, a bounded body). SLB answers ``{"orders": [...]}`` (``204`` or an empty list when it
has none); ``sinks.slb.order`` reads each order.

Each order is answered with ``POST {base_url}/orders/<order_id>/receipt``:

- ``received`` once ``publish`` returned True (the event is held durably), so SLB stops
  offering it. If ``publish`` returns False nothing is answered: SLB offers it again at the
  next poll and it is published then;
- ``rejected``, with a reason that starts with the offending field's path, for an order that
  is malformed (bad time, unknown task, an MGRS reference that does not decode ...), so SLB's
  operator sees why. It is counted and logged at most once per ``_LOG_INTERVAL_S`` by outcome.

Then each ``OrderStatus`` of its orders from the orders processor (``accepted``, ``rejected``
with the check and its numbers, ``executing``, ``completed``, ``failed``) is POSTed to the
same receipt URL as it comes (``on_order_status``; at most ``max_pending_statuses`` wait,
the oldest are dropped and counted). A status SLB does not take (unreachable, 5xx) is sent
again after ``poll_interval_s``; a 4xx answer drops it, counted.

Answers are remembered (the newest ``max_remembered``): an order offered again after it was
answered (the receipt was lost, say) is answered again, not published again. An order offered
again under a taken ``order_id`` with other content (``FiveLineOrder.content_digest``) is
answered ``conflict`` (``order_id: ... was already taken with other content ...``) and not
published: the first stands, a changed order needs a new id. An element of
the list without a usable ``order_id`` cannot be answered; it is counted as ``unanswerable``.
Nothing SLB sends can stop the source: every failure is counted in ``counts`` and shown on
/status. Whether an order is *accepted* is the orders processor's answer, not this one's.
Statuses are held in memory: after a restart, SLB learns only the states reached since.
"""

from __future__ import annotations

import ssl
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from datetime import datetime
from importlib.metadata import PackageNotFoundError, version
from typing import Any, ClassVar
from urllib.parse import quote

import anyio
import anyio.abc
import httpx
import structlog
from pydantic import Field

from gateway.c2.source import SourceConfig
from gateway.clock import utc_now
from gateway.errors import OrderRejected
from gateway.events import Event, OrderStatus
from gateway.ops.logsetup import RateLimit
from gateway.transports.endpoint import HttpsEndpoint
from gateway.transports.https import (
    classify_answer,
    describe_https_error,
    https_client,
    read_at_most,
)
from gateway.transports.tls import tls_problem
from sinks.slb.order import order_id_of, parse_order_list, read_order, receipt_payload

__all__ = ["SlbSource", "SlbSourceConfig"]

log = structlog.get_logger(__name__)

_LOG_INTERVAL_S = 10.0
#: How much of an error answer's body is read and quoted, at most.
_MAX_REASON_BYTES = 512


class SlbSourceConfig(SourceConfig, HttpsEndpoint):
    """Options of the SLB order source (beside ``name`` and ``type: slb``)."""

    poll_interval_s: float = Field(
        default=5.0, gt=0, le=3600, description="Seconds between two polls of /orders."
    )
    max_orders: int = Field(
        default=100, ge=1, le=1000, description="Orders asked for (?limit=) and read per poll."
    )
    max_body_bytes: int = Field(
        default=1 << 20,
        ge=1024,
        le=16 << 20,
        description="Largest /orders answer read; a longer one is refused and counted.",
    )
    max_retry_after_s: float = Field(
        default=300.0, ge=0, le=3600, description="Longest wait a 429's or 503's Retry-After sets."
    )
    max_remembered: int = Field(
        default=10_000, ge=1, le=1_000_000, description="Answered orders remembered."
    )
    max_pending_statuses: int = Field(
        default=1000, ge=1, le=100_000, description="Order statuses waiting to be POSTed."
    )


def _package_version() -> str:
    try:
        return version("fischer-gateway")
    except PackageNotFoundError:
        return "0"


class SlbSource:
    """Polls SLB for orders, publishes each, and answers it with a receipt."""

    config_model: ClassVar[type[SlbSourceConfig]] = SlbSourceConfig

    def __init__(
        self,
        name: str,
        config: SlbSourceConfig,
        publish: Callable[[Event], bool],
        *,
        clock: Callable[[], datetime] = utc_now,
    ) -> None:
        # Built at config load (check-config, run): unusable TLS material is a config error.
        problem = tls_problem(config.tls_files)
        if problem is not None:
            raise ValueError(problem)
        self.name = name
        self.config = config
        self._publish = publish
        self._clock = clock
        self.orders_url = config.url("/orders")
        self._files = config.tls_files
        #: Orders and polls by outcome (see the module docstring).
        self.counts: Counter[str] = Counter()
        #: Receipts by order id, in the order they were made (oldest first), with the digest
        #: of the order taken (None for one rejected as malformed).
        self._answered: OrderedDict[str, tuple[dict[str, Any], str | None]] = OrderedDict()
        self._log_limit = RateLimit(interval_s=_LOG_INTERVAL_S)
        self._received_log = RateLimit(interval_s=1.0)
        self._headers = {
            "Accept": "application/json",
            "User-Agent": f"fischer-gateway/{_package_version()}",
        }
        self._statuses: deque[OrderStatus] = deque()
        self._status_ready = anyio.Event()
        self._receipt_lock = anyio.Lock()
        self.log = log.bind(source=name, url=self.orders_url)

    def on_order_status(self, status: OrderStatus) -> None:
        """Queue a status of one of this source's orders for SLB; never blocks."""
        if status.source != self.name:
            return
        if len(self._statuses) >= self.config.max_pending_statuses:
            self._statuses.popleft()
            self._count("status_dropped", order_id=status.order_id)
        self._statuses.append(status)
        self._status_ready.set()

    def status(self) -> dict[str, object]:
        """What /status shows for this source."""
        return {
            "source": self.name,
            "type": "slb",
            "url": self.orders_url,
            "counts": dict(self.counts),
            "remembered": len(self._answered),
        }

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Load the TLS material, report started, then poll until cancelled.

        Raises ``OSError``, ``ssl.SSLError`` or ``ValueError`` naming the file when the TLS
        material cannot be loaded (the supervisor retries and shows it on /status).
        """
        timeout_s = self.config.timeout_s
        client = await https_client(
            self._files,
            connect_timeout_s=timeout_s,
            read_timeout_s=timeout_s,
            write_timeout_s=timeout_s,
            pool_timeout_s=timeout_s,
            max_connections=1,
        )
        try:
            async with anyio.create_task_group() as tg:
                tg.start_soon(self._report_statuses, client)
                task_status.started()
                while True:
                    wait_s = await self.poll(client)
                    await anyio.sleep(wait_s)
        finally:
            with anyio.move_on_after(timeout_s, shield=True):
                await client.aclose()

    async def _report_statuses(self, client: httpx.AsyncClient) -> None:
        while True:
            await self._status_ready.wait()
            self._status_ready = anyio.Event()
            while self._statuses:
                status = self._statuses[0]
                receipt = receipt_payload(
                    status.order_id,
                    status.status.value,
                    time=status.time,
                    reason=_reason(status),
                    event_id=status.event_id,
                    seq=status.seq,
                )
                outcome = await self._acknowledge(client, status.order_id, receipt)
                if outcome == "retry":
                    await anyio.sleep(self.config.poll_interval_s)
                    continue
                if self._statuses and self._statuses[0] is status:
                    self._statuses.popleft()

    def _count(self, outcome: str, **fields: object) -> None:
        self.counts[outcome] += 1
        if self._log_limit.allow(outcome):
            self.log.warning("slb_orders_problem", outcome=outcome, **fields)

    async def _request(
        self, client: httpx.AsyncClient, method: str, url: str, limit: int, **kwargs: Any
    ) -> tuple[int, httpx.Headers, bytes] | str:
        """One request under the deadline: (status, headers, at most ``limit`` bytes) or why not."""
        try:
            with anyio.fail_after(self.config.timeout_s):
                async with client.stream(method, url, headers=self._headers, **kwargs) as answer:
                    body = await read_at_most(answer, limit)
                    return answer.status_code, answer.headers, body
        except TimeoutError:
            return f"{url}: no answer within {self.config.timeout_s} s"
        except (httpx.HTTPError, ssl.SSLError, OSError) as exc:
            return describe_https_error(exc, url, self._files)

    async def poll(self, client: httpx.AsyncClient) -> float:
        """Ask for orders once and answer each; the seconds to wait before the next poll."""
        interval_s = self.config.poll_interval_s
        limit = self.config.max_orders
        got = await self._request(
            client,
            "GET",
            self.orders_url,
            self.config.max_body_bytes + 1,
            params={"limit": limit},
        )
        if isinstance(got, str):
            self._count("poll_failed", detail=got)
            return interval_s
        status, headers, body = got
        self.counts["polls"] += 1
        if status == 204:
            return interval_s
        if status != 200:
            text = body[:_MAX_REASON_BYTES].decode("utf-8", "replace").strip()
            answer = classify_answer(
                self.orders_url,
                status,
                headers,
                text,
                max_retry_after_s=self.config.max_retry_after_s,
            )
            self._count("poll_refused", status=status, detail=answer.detail)
            return max(interval_s, answer.retry_after_s or 0.0)
        if len(body) > self.config.max_body_bytes:
            self._count("oversize", limit_bytes=self.config.max_body_bytes)
            return interval_s
        try:
            elements = parse_order_list(body, max_orders=limit)
        except ValueError as exc:
            self._count("malformed_list", detail=str(exc))
            return interval_s
        for element in elements:
            await self._take(client, element)
        return interval_s

    async def _take(self, client: httpx.AsyncClient, element: object) -> None:
        order_id = order_id_of(element)
        if order_id is None:
            self._count("unanswerable", detail="no usable order_id")
            return
        answered = self._answered.get(order_id)
        if answered is not None:
            await self._reoffered(client, order_id, element, *answered)
            return
        digest: str | None = None
        try:
            order = read_order(element, source=self.name)
        except OrderRejected as exc:
            self._count("rejected", order_id=order_id, reason=str(exc))
            receipt = receipt_payload(order_id, "rejected", time=self._clock(), reason=str(exc))
        else:
            if not self._publish(order):
                # Not held: no receipt, so SLB offers it again and it is published then.
                self._count("not_held", order_id=order_id)
                return
            self.counts["received"] += 1
            if self._received_log.allow("received"):  # a flood of orders: one line a second
                self.log.info(
                    "slb_order_received",
                    received_total=self.counts["received"],
                    order_id=order_id,
                    task=order.task.value,
                    priority=order.priority.value,
                )
            receipt = receipt_payload(
                order_id, "received", time=self._clock(), event_id=order.event_id
            )
            digest = order.content_digest()
        self._answered[order_id] = (receipt, digest)
        while len(self._answered) > self.config.max_remembered:
            self._answered.popitem(last=False)
        await self._acknowledge(client, order_id, receipt)

    async def _reoffered(
        self,
        client: httpx.AsyncClient,
        order_id: str,
        element: object,
        receipt: dict[str, Any],
        digest: str | None,
    ) -> None:
        """Answer an order offered again: its receipt again, or ``conflict`` if it changed."""
        if digest is not None:
            try:
                again = read_order(element, source=self.name).content_digest()
            except OrderRejected:
                again = None
            if again != digest:
                self._count("conflict", order_id=order_id)
                reason = (
                    f"order_id: {order_id} was already taken with other content; the first"
                    " stands: give a changed order a new id"
                )
                conflict = receipt_payload(order_id, "conflict", time=self._clock(), reason=reason)
                await self._acknowledge(client, order_id, conflict)
                return
        self.counts["reoffered"] += 1
        await self._acknowledge(client, order_id, receipt)

    async def _acknowledge(
        self, client: httpx.AsyncClient, order_id: str, receipt: dict[str, Any]
    ) -> str:
        """POST one receipt: "done" (taken, or nothing left to answer), "retry" or "refused"."""
        url = self.config.url(f"/orders/{quote(order_id, safe='')}/receipt")
        # One receipt at a time, first come first served: an order's "received" goes before
        # the statuses the orders processor already published while it was being sent.
        async with self._receipt_lock:
            got = await self._request(client, "POST", url, _MAX_REASON_BYTES, json=receipt)
        if isinstance(got, str):
            self._count("receipt_failed", order_id=order_id, detail=got)
            return "retry"
        status, headers, body = got
        if status == 404:
            # SLB no longer knows the order (withdrawn): there is nothing left to answer.
            self.counts["receipt_unknown_order"] += 1
            return "done"
        text = body.decode("utf-8", "replace").strip()
        answer = classify_answer(url, status, headers, text, max_retry_after_s=0.0)
        if answer.outcome in ("delivered", "duplicate"):
            self.counts[f"receipt_{receipt['status']}"] += 1
            return "done"
        self._count("receipt_failed", order_id=order_id, detail=answer.detail)
        return "retry" if answer.outcome == "retry" else "refused"


def _reason(status: OrderStatus) -> str | None:
    """The receipt's reason: the check's name, a colon, its numbers (the schema's form)."""
    if status.reason is None:
        return None
    return status.reason if status.check is None else f"{status.check}: {status.reason}"
