"""Drives one sink: its queue, batching, retry with backoff, dead letters and metrics.

Every sink gets the same delivery behaviour from here, and holds none of its own:

- latest-wins kinds (telemetry, link state, blue force) sit in one slot per key, so a slow
  sink gets the freshest value instead of a backlog;
- durable kinds (detections, tracks, ...) are held in the spool (``gateway.spool``) until the
  sink confirms them, with a window of them in memory (``gateway.c2.outbox``): they survive a
  restart or kill -9 of the gateway, a permanent rejection is dead-lettered in the spool, a
  stale event is delivered marked late or expired by its kind's rule; only a full spool
  refuses events (counted and logged loudly);
- the runner waits once (a plain future and one timer), takes everything ready up to
  ``batch_max``, sends it as one batch under one deadline (``asyncio.timeout``: no cancel
  scope per event) and confirms it in the spool's group commit of the loop pass
  (``gateway.spool.group``); a hung sink costs that sink a timeout and a retry, never another
  sink or the ingest path (``offer`` is synchronous and O(1));
- a sink that can send without awaiting (``gateway.c2.sink.SendsNow``) is not woken at all
  while idle: the offer puts its runner on the loop pass's one delivery pass
  (``gateway.c2.deliverypass``), which takes, sends and confirms for every such runner in
  one callback; what the sink cannot take at once (a full buffer, an error) wakes the runner,
  which delivers it as below;
- a sink bug (an exception that is neither a ``SinkError`` nor the network's) is retried
  ``ERROR_ATTEMPTS`` times, then the batch is tried event by event and only the events that
  still fail are given up on, so one poisoned event cannot block the queue;
- a sink's background work (its optional ``run`` lifetime) runs in this runner's task group,
  between ``open`` and ``aclose``, never in a task group the sink holds itself.

Failures go through one circuit breaker per sink (``gateway.c2.circuit``): jittered exponential
backoff from tenacity, and after a few failures in a row one probe event at a time until the
sink takes events again.
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections import deque
from collections.abc import Mapping
from typing import Any, cast

import anyio
import anyio.abc
import anyio.lowlevel
import structlog

from gateway.c2.circuit import Circuit, CircuitState
from gateway.c2.deliverypass import DeliveryPass
from gateway.c2.outbox import Outbox, Queued
from gateway.c2.sink import LifetimeSink, Sink
from gateway.config import SinkEntry, StaleRule
from gateway.errors import PermanentSinkError, SpoolError, TransientSinkError
from gateway.events import LATEST_WINS_KINDS, Event, EventKind, latest_key
from gateway.ops.instruments import Instruments
from gateway.ops.logsetup import RateLimit
from gateway.ops.pluginstatus import read_status
from gateway.spool.store import Spool

__all__ = ["DEAD_LETTER_KEEP", "ERROR_ATTEMPTS", "IDLE_POLL_S", "MAX_LATEST_SLOTS", "SinkRunner"]

log = structlog.get_logger(__name__)

#: The newest dead-lettered events kept in memory too, for tests and /status (the spool has all).
DEAD_LETTER_KEEP = 1000
#: Latest-wins slots held for one sink at most (units reported over CoT, airframes ...).
MAX_LATEST_SLOTS = 10_000

#: Unexpected errors (sink bugs) in a row on one batch before its events are tried one by one
#: and those that still fail are given up on (dead-lettered, or counted if latest-wins).
ERROR_ATTEMPTS = 3
_ERROR_LOG_INTERVAL_S = 30.0
#: While idle, how often the runner looks in the spool for re-queued dead letters.
IDLE_POLL_S = 5.0


def _is_transient(exc: BaseException) -> bool:
    """Worth retrying as it is: said so, a deadline, or the network (an untranslated OSError)."""
    return isinstance(exc, TransientSinkError | TimeoutError | OSError)


def _release(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)


class _StartedFlag:
    """Forwards ``started()`` to the runner's task status and remembers that it was called."""

    def __init__(self, status: anyio.abc.TaskStatus[None]) -> None:
        self._status = status
        self.is_started = False

    def started(self, value: None = None) -> None:
        self.is_started = True
        self._status.started(value)


class SinkRunner:
    """Owns the queues of one sink and the task that feeds it."""

    def __init__(
        self,
        entry: SinkEntry,
        sink: Sink,
        instruments: Instruments,
        *,
        spool: Spool | None = None,
        stale: Mapping[EventKind, StaleRule] | None = None,
        delivery: DeliveryPass | None = None,
    ) -> None:
        """``delivery``: the pass shared by the runners of one gateway (its own if None)."""
        self.entry = entry
        self.sink = sink
        self.name = entry.name
        self.kinds = sink.kinds
        self._latest: dict[str, Queued] = {}
        #: Without a spool of the gateway's, the runner keeps its own in memory (tests, tools).
        self.spool = spool if spool is not None else Spool()
        self.outbox = Outbox(self.name, self.spool, window=entry.queue_max, stale=stale)
        self._waiter: asyncio.Future[None] | None = None
        self._waiting = False
        send_now = getattr(sink, "send_now", None)
        if inspect.iscoroutinefunction(send_now):
            # Called without an await it would only make a coroutine (and a warning) per
            # pass: the sink is served by its task instead (``check_sink`` refuses it).
            log.warning(
                "sink_send_now_ignored",
                sink=self.name,
                reason="send_now is async; it must be a plain method (gateway.c2.sink.SendsNow)",
            )
            send_now = None
        #: The sink's synchronous send (``SendsNow``), None if it has none.
        self._send_now = send_now if callable(send_now) else None
        self._delivery = delivery if delivery is not None else DeliveryPass()
        self._in_pass = False
        #: Events delivered by the delivery pass, without waking this runner's task.
        self.sent_in_pass = 0
        self._stopping = False
        self._done = anyio.Event()
        self._stop_requested = anyio.Event()
        self._lifetime_failure: BaseException | None = None
        self._error_attempts = 0
        self._needs_close = False
        self._error_log = RateLimit(interval_s=_ERROR_LOG_INTERVAL_S)
        self.circuit = Circuit(initial_s=entry.retry_initial_s, max_s=entry.retry_max_s)
        self.dead_letters: deque[tuple[Event, str]] = deque(maxlen=DEAD_LETTER_KEEP)
        self.state = "starting"
        self.reason = ""
        self.is_open = False
        self.close_timeout_s = entry.send_timeout_s
        inst = instruments
        self._sent = inst.sink_sent.labels(self.name)
        self._superseded = inst.sink_superseded.labels(self.name)
        self._overflow = inst.sink_dropped.labels(self.name, "overflow")
        self._rejected = inst.sink_dropped.labels(self.name, "rejected")
        self._given_up = inst.sink_dropped.labels(self.name, "error")
        self._expired = inst.sink_dropped.labels(self.name, "expired")
        self._late = inst.sink_late
        self._latency = inst.sink_latency.labels(self.name)
        self._open_gauge = inst.sink_open.labels(self.name)
        self._circuit_gauge = inst.sink_circuit.labels(self.name)
        self._failed = {
            reason: inst.sink_failed.labels(self.name, reason)
            for reason in ("transient", "timeout", "error", "permanent")
        }
        self._overflow_log = RateLimit(interval_s=5.0)
        self._expired_log = RateLimit(interval_s=10.0)
        self._reject_log = RateLimit(interval_s=10.0)
        self._expired_some = False
        self.log = log.bind(sink=self.name)

    @property
    def description(self) -> str:
        """How config errors name this runner's sink."""
        return f"sink {self.name!r} ({self.entry.type})"

    @property
    def failures_in_row(self) -> int:
        """Failed calls in a row (the circuit breaker's count)."""
        return self.circuit.failures_in_row

    @failures_in_row.setter
    def failures_in_row(self, value: int) -> None:
        self.circuit.failures_in_row = value

    # -- ingest side: synchronous, O(1), never blocks ------------------------------------

    def offer(self, event: Event, ingest_mono: float) -> None:
        """Queue ``event`` by its kind's policy; wake the sender."""
        self.offer_slot(event, ingest_mono, latest_key(event))

    def offer_slot(self, event: Event, ingest_mono: float, slot: str | None) -> None:
        """``offer`` with the event's ``latest_key`` already computed (once, by the bus).

        A durable event is spooled for this sink alone here; the bus spools one copy for all
        its sinks instead and calls ``offer_spooled``.
        """
        if slot is not None:
            latest = self._latest
            if slot in latest:
                self._superseded.inc()
                del latest[slot]  # re-inserted below: the dict stays oldest-first
            elif len(latest) >= MAX_LATEST_SLOTS:
                # Slots are keyed by airframe, uid ... from the network: while a sink is down
                # the oldest latest-wins report makes room (counted like an overflow).
                del latest[next(iter(latest))]
                self._overflow.inc()
            latest[slot] = Queued(event, ingest_mono, 0, 0.0)  # never spooled: no clock read
        else:
            try:
                held = self.outbox.append(event, ingest_mono)
            except SpoolError:
                held = False
                self.log.exception("spool_write_failed", event_id=event.event_id)
            if not held:
                self.refused(event)
                return
        if self._waiting:
            self._nudge()

    def offer_spooled(self, event: Event, ingest_mono: float, seq: int) -> None:
        """Queue a durable event the bus has already spooled for this sink as ``seq``."""
        self.outbox.add(event, ingest_mono, seq)
        if self._waiting:
            self._nudge()

    def _nudge(self) -> None:
        """Something is ready for an idle runner: the delivery pass sends it, or the task."""
        if self._send_now is None:
            self._wake_sender()
        elif not self._in_pass:
            self._in_pass = self._delivery.ready(self)
            if not self._in_pass:
                self._wake_sender()

    def refused(self, event: Event) -> None:
        """Count a durable event the spool had no room for (the spool logs it too)."""
        self._overflow.inc()
        if self._overflow_log.allow("overflow"):
            self.log.error(
                "sink_event_refused_spool_full",
                kind=event.kind.value,
                event_id=event.event_id,
                note="the spool is full: durable events are refused until sinks catch up",
            )

    def wake(self) -> None:
        """Wake the runner's task if it is idle (the delivery pass hands work back by this)."""
        self._wake_sender()

    def _wake_sender(self) -> None:
        if self._waiting:
            self._waiting = False
            waiter = self._waiter
            if waiter is not None and not waiter.done():
                waiter.set_result(None)

    @property
    def depth(self) -> tuple[int, int]:
        """Events waiting: (latest-wins slots, durable events the spool owes this sink)."""
        return len(self._latest), self.outbox.owed

    def stop(self) -> None:
        """Ask the runner to finish: it drains what is queued, then closes the sink.

        With a spool on disk, a sink that is failing is not drained: what it is owed stays
        in the spool for the next start.
        """
        self._stopping = True
        self._stop_requested.set()
        self._wake_sender()

    async def wait_done(self) -> None:
        """Wait until ``run`` has returned."""
        await self._done.wait()

    @property
    def _leave_rest_in_spool(self) -> bool:
        return (
            self._stopping
            and self.spool.path is not None
            and (self.circuit.failures_in_row > 0 or not self.is_open)
            and not self._latest
        )

    # -- delivery side -------------------------------------------------------------------

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Open the sink (retrying), deliver until stopped and drained, then close it.

        A sink with a ``run`` lifetime gets it started in this runner's task group after each
        successful ``open`` and cancelled before ``aclose``; if it fails, the sink is closed
        and opened again with backoff.
        """
        task_status.started()
        self._circuit_gauge.set(0.0)
        try:
            while await self._open():
                failure = await self._serve()
                if failure is None:
                    break
                await self._close()
                await self._backoff("run", failure)
        finally:
            with anyio.move_on_after(self.close_timeout_s, shield=True):
                await self._close()
            self.state = "closed"
            self._done.set()

    async def _close(self) -> None:
        if not self._needs_close:
            return
        self._needs_close = False
        self.is_open = False
        self._open_gauge.set(0.0)
        try:
            await self.sink.aclose()
        except Exception:
            self.log.exception("sink_close_failed")

    async def _open(self) -> bool:
        """Open the sink, retrying; False if asked to stop with nothing left to deliver."""
        while True:
            if self._stopping and (not any(self.depth) or self._leave_rest_in_spool):
                return False
            self._needs_close = True  # ``aclose`` is due even after a failed ``open``
            try:
                with anyio.fail_after(self.entry.send_timeout_s):
                    await self.sink.open()
            except Exception as exc:  # noqa: BLE001 - isolation boundary around one sink call
                await self._backoff("open", exc)
                continue
            self.is_open = True
            self._open_gauge.set(1.0)
            self.state, self.reason = "open", ""
            self.log.info("sink_opened")
            return True

    async def _serve(self) -> BaseException | None:
        """Deliver until stopped and drained (None), or until the sink's lifetime fails."""
        self._lifetime_failure = None
        outcome: BaseException | None = None
        async with anyio.create_task_group() as tg:
            try:
                if callable(getattr(self.sink, "run", None)):
                    try:
                        with anyio.fail_after(self.entry.send_timeout_s):
                            await tg.start(self._lifetime)
                    except Exception as exc:  # noqa: BLE001 - isolation boundary, one sink call
                        outcome = exc
                if outcome is None:
                    outcome = await self._deliver_until_done()
            finally:
                tg.cancel_scope.cancel()
        return outcome

    async def _lifetime(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        status = _StartedFlag(task_status)
        try:
            await cast("LifetimeSink", self.sink).run(task_status=status)
        except Exception as exc:
            if not status.is_started:
                raise  # comes out of ``tg.start`` in ``_serve``
            self._lifetime_failure = exc
            self._wake_sender()

    async def _deliver_until_done(self) -> BaseException | None:
        while True:
            if self._lifetime_failure is not None:
                return self._lifetime_failure
            if self._leave_rest_in_spool:
                return None
            items = self._take()
            if not items and self._expired_some:
                await anyio.lowlevel.checkpoint()  # a stale backlog: a batch at a time
                continue
            if not items:
                if self._stopping:
                    return None
                await self._idle()
                if not self._latest and not len(self.outbox):
                    self.outbox.poll()  # dead letters re-queued from the command line
                continue
            await self._deliver(items)

    def deliver_now(self) -> None:
        """The delivery pass: send what is ready with the sink's ``send_now``, no await.

        Only while the task waits idle (nothing taken, nothing in flight) with the sink open,
        the circuit closed and no stop asked, so a batch sent here never overtakes another of
        this sink's; otherwise, and for whatever the sink did not take at once, the task is
        woken and delivers as ever (deadline, retry, backoff, dead letters).
        """
        self._in_pass = False
        waiter, send_now = self._waiter, self._send_now
        if waiter is None or waiter.done() or not self._waiting:
            return  # the task is on its way and takes what is ready itself
        if (
            send_now is None
            or self._stopping
            or not self.is_open
            or self.circuit.failures_in_row
            or self._lifetime_failure is not None
        ):
            self._wake_sender()
            return
        latest = self._latest
        whole = self.outbox.drained and len(latest) <= self.entry.batch_max
        if whole:
            items = list(latest.values())  # latest-wins values only: no spool involved
            latest.clear()
        else:
            items = self._take()  # commits the spool's open appends first (``Outbox.take``)
        if items:
            try:
                done = send_now([item.event for item in items])
            except Exception:  # noqa: BLE001 - the task's ``send`` meets it and handles it
                done = 0
            count = len(items)
            if done != count:
                done = min(max(done, 0), count) if type(done) is int else 0
            if done:
                self._error_attempts = 0
                self.sent_in_pass += done
                self._delivered(items if done == count else items[:done])
            if done < count:
                self._put_back(items[done:])
                self._wake_sender()
                return
        if not whole and (self._expired_some or self._latest or len(self.outbox)):
            self._wake_sender()  # more than one batch ready, or a stale backlog

    async def _idle(self) -> None:
        """Wait for an offer, a stop or ``IDLE_POLL_S``: a plain future and one timer, the
        cheapest wait the loop has (no cancel scope per wait)."""
        loop = asyncio.get_running_loop()
        self._in_pass = False  # a pass of a loop that ended without running it
        waiter = self._waiter = loop.create_future()
        timer = loop.call_later(IDLE_POLL_S, _release, waiter)
        self._waiting = True
        try:
            await waiter
        finally:
            timer.cancel()
            self._waiting = False
            self._waiter = None

    def _take(self) -> list[Queued]:
        limit = 1 if self.circuit.probing() else self.entry.batch_max
        self._circuit_gauge.set(float(self.circuit.state))
        items: list[Queued] = []
        if self._latest:
            if len(self._latest) <= limit:
                items.extend(self._latest.values())
                self._latest.clear()
            else:
                for key in list(self._latest)[:limit]:
                    items.append(self._latest.pop(key))
        self._expired_some = False
        if len(items) < limit:
            durable, expired = self.outbox.take(limit - len(items))
            if expired:
                # One dead-letter write per reason and at most one log line per interval.
                self._expired_some = True
                self._expired.inc(len(expired))
                by_reason: dict[str, list[Queued]] = {}
                for item, reason in expired:
                    by_reason.setdefault(reason, []).append(item)
                for reason, group in by_reason.items():
                    self._dead_letter(group, reason, count=False, log_it=False)
                if self._expired_log.allow("expired"):
                    self.log.warning(
                        "sink_events_expired",
                        count=len(expired),
                        expired_total=int(self._expired.value),
                        reason=next(iter(by_reason)),
                    )
            items += durable
        return items

    def _put_back(self, items: list[Queued]) -> None:
        self.outbox.put_back([item for item in items if item.seq])
        for item in items:
            slot = latest_key(item.event)
            if slot is not None:
                # A newer value that arrived during the failed send wins over the retry.
                self._latest.setdefault(slot, item)

    async def _send(self, items: list[Queued]) -> BaseException | None:
        """One ``send`` under the deadline: None if delivered, else what it raised.

        Cancelled mid-send (shutdown), the events are put back: the batch is still ours. The
        deadline is the loop's own (``asyncio.timeout``: one timer, no cancel scope), one per
        batch.
        """
        settled = False
        try:
            async with asyncio.timeout(self.entry.send_timeout_s):
                await self.sink.send([item.event for item in items])
            settled = True
        except Exception as exc:  # noqa: BLE001 - isolation boundary around one sink call
            settled = True
            return exc
        finally:
            if not settled:
                self._put_back(items)
        return None

    async def _deliver(self, items: list[Queued]) -> None:
        failure = await self._send(items)
        if failure is None:
            self._error_attempts = 0
            self._delivered(items)
        elif isinstance(failure, PermanentSinkError):
            self._error_attempts = 0
            self._refused(items, failure)
        elif _is_transient(failure):
            self._error_attempts = 0
            self._put_back(items)
            await self._backoff("send", failure)
        else:
            self._error_attempts += 1
            if self._error_attempts < ERROR_ATTEMPTS:
                self._put_back(items)
                await self._backoff("send", failure)
                return
            self._error_attempts = 0
            self._failed["error"].inc()
            await self._deliver_one_by_one(items, failure)

    async def _deliver_one_by_one(self, items: list[Queued], failure: BaseException) -> None:
        """The batch failed ``ERROR_ATTEMPTS`` times with a sink bug: isolate the culprits."""
        if len(items) == 1:
            self._give_up(items[0], failure)
            return
        for index, item in enumerate(items):
            failure_one = await self._send([item])
            if failure_one is None:
                self._delivered([item])
            elif isinstance(failure_one, PermanentSinkError):
                self._refused([item], failure_one)
            elif _is_transient(failure_one):
                self._put_back(items[index:])
                await self._backoff("send", failure_one)
                return
            else:
                self._failed["error"].inc()
                self._give_up(item, failure_one)

    def _delivered(self, items: list[Queued]) -> None:
        now = time.monotonic()
        # The batch's latencies in one call; then the spooled events (seq > 0) alone, the only
        # ones the spool owes and the only ones ``Outbox.take`` can have marked late.
        if len(items) == 1:
            self._latency.observe(now - items[0].ingest_mono)  # below saturation: the usual
        else:
            self._latency.observe_many([now - item.ingest_mono for item in items])
        if durable := [item for item in items if item.seq]:
            for item in durable:
                # The field's value straight from the model's dict: on a kind without the
                # field, getattr would fall into pydantic's slow __getattr__ for every event.
                if item.event.__dict__.get("late_by_s") is not None:
                    self._late.labels(self.name, item.event.kind.value).inc()
            self._confirm(durable)
        self._sent.inc(len(items))
        circuit = self.circuit
        if not circuit.failures_in_row and circuit.state is CircuitState.CLOSED:
            return  # closed already, and its gauge says so (set at each take and failure)
        ended = circuit.succeeded()
        self._circuit_gauge.set(0.0)
        if ended:
            self.log.info("sink_recovered", after_failures=ended)
            self.state, self.reason = "open", ""

    def _confirm(self, durable: list[Queued]) -> None:
        """The sink has these spooled events (every one with a ``seq``)."""
        try:
            self.outbox.confirm(durable)
        except SpoolError:
            # Delivered but still in the spool: sent again after a restart (the receiver
            # de-duplicates by event id). Logged, never fatal.
            self.log.exception("spool_confirm_failed", count=len(durable))

    def _refused(self, items: list[Queued], exc: PermanentSinkError) -> None:
        """Dead-letter what ``exc`` names (the whole batch if it names nothing)."""
        self._failed["permanent"].inc()
        if not exc.event_ids:
            self._dead_letter(items, str(exc))
            return
        refused = [item for item in items if item.event.event_id in exc.event_ids]
        if exc.reasons:
            # Each event keeps its own reason; one log line for the batch.
            by_reason: dict[str, list[Queued]] = {}
            for item in refused:
                by_reason.setdefault(exc.reasons.get(item.event.event_id, str(exc)), []).append(
                    item
                )
            for reason, group in by_reason.items():
                self._dead_letter(group, reason, count=False, log_it=False)
                self._rejected.inc(len(group))
            if self._reject_log.allow("dead_letter"):
                self.log.error("sink_events_rejected", count=len(refused), reason=str(exc)[:500])
        else:
            self._dead_letter(refused, str(exc))
        self._delivered([item for item in items if item.event.event_id not in exc.event_ids])
        if strangers := len(exc.event_ids) - len(refused):
            self.log.warning("sink_refused_unknown_events", count=strangers)

    def _give_up(self, item: Queued, exc: BaseException) -> None:
        reason = f"sink error after {ERROR_ATTEMPTS} attempts: {type(exc).__name__}: {exc}"
        if item.event.kind in LATEST_WINS_KINDS:
            self._given_up.inc()  # superseded soon anyway; counted, not dead-lettered
        else:
            self._dead_letter([item], reason, count=False, log_it=False)
            self._rejected.inc()
        if not self._reject_log.allow("given_up"):
            return
        self.log.error(
            "sink_event_given_up",
            kind=item.event.kind.value,
            event_id=item.event.event_id,
            reason=reason,
        )

    def _dead_letter(
        self, items: list[Queued], reason: str, *, count: bool = True, log_it: bool = True
    ) -> None:
        durable = [item for item in items if item.event.kind not in LATEST_WINS_KINDS]
        for item in durable:
            self.dead_letters.append((item.event, reason))
            if count:
                self._rejected.inc()
        try:
            self.outbox.dead_letter([item for item in durable if item.seq], reason)
        except SpoolError:
            self.log.exception("spool_dead_letter_failed", count=len(durable))
        if not log_it or not self._reject_log.allow("dead_letter"):
            return  # counted in fg_sink_events_dropped_total whatever the log says
        if count:
            self.log.error("sink_events_rejected", count=len(items), reason=reason[:500])
        elif durable:
            self.log.warning("sink_events_dead_lettered", count=len(durable), reason=reason[:200])

    def retry_delay_s(self) -> float:
        """The longest backoff before the next attempt for ``failures_in_row`` (no jitter)."""
        doublings = min(max(self.failures_in_row - 1, 0), 64)
        return float(min(self.entry.retry_max_s, self.entry.retry_initial_s * 2.0**doublings))

    async def _backoff(self, step: str, exc: BaseException) -> None:
        if isinstance(exc, TimeoutError):
            reason, detail = "timeout", f"{step} exceeded {self.entry.send_timeout_s} s"
        elif _is_transient(exc):
            reason, detail = "transient", str(exc)
        else:
            reason, detail = "error", f"{type(exc).__name__}: {exc}"
        self._failed[reason].inc()
        delay = self.circuit.failed()
        self._circuit_gauge.set(float(self.circuit.state))
        self.state, self.reason = "retrying", detail
        fields: dict[str, Any] = {
            "step": step,
            "reason": reason,
            "detail": detail,
            "failures_in_row": self.failures_in_row,
            "circuit": self.circuit.state.name.lower(),
            "retry_in_s": round(delay, 3),
        }
        if reason != "error":
            if self.failures_in_row <= self.circuit.threshold or self._error_log.allow(step):
                self.log.warning("sink_call_failed", **fields)
        elif self._error_log.allow(step):
            # A sink bug: the traceback once per interval, every occurrence counted.
            self.log.warning("sink_call_failed", exc_info=exc, **fields)
        if self._stopping:
            # Draining at shutdown: do not wait out a long backoff; the deadline decides.
            delay = min(delay, 0.1)
        with anyio.move_on_after(delay):
            await self._stop_requested.wait()

    def _dead_letters_held(self) -> int:
        try:
            return self.spool.dead_letters_of(self.name)
        except SpoolError:  # /status after the spool closed at shutdown
            return len(self.dead_letters)

    def outcome_counts(self) -> Mapping[str, int]:
        """The sink's own monotonic counts (its optional ``counts()``), for /metrics."""
        own = getattr(self.sink, "counts", None)
        return cast("Mapping[str, int]", own()) if callable(own) else {}

    def status(self) -> dict[str, object]:
        """The runner's state for /status, and the sink's own under ``detail`` if it has one."""
        latest, durable = self.depth
        own = getattr(self.sink, "status", None)
        detail = read_status(own, f"sink {self.name}") if callable(own) else None
        return {
            "sink": self.name,
            "type": self.entry.type,
            "state": self.state,
            "reason": self.reason,
            "open": self.is_open,
            "circuit": self.circuit.state.name.lower(),
            "failures_in_row": self.failures_in_row,
            "queued_latest": latest,
            "queued_durable": durable,
            "queue_max": self.entry.queue_max,
            "dead_letters": self._dead_letters_held(),
            "sent": int(self._sent.value),
            "sent_in_pass": self.sent_in_pass,
            **({"detail": detail} if detail is not None else {}),
        }
