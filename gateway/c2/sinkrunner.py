"""Drives one sink: its queue, batching, retry with backoff, dead letters and metrics.

Every sink gets the same delivery behaviour from here, and holds none of its own:

- latest-wins kinds (telemetry, link state, blue force) sit in one slot per key, so a slow
  sink gets the freshest value instead of a backlog;
- durable kinds (detections, tracks, ...) sit in a bounded FIFO and are never dropped
  silently: an overflow is counted and logged loudly, a permanent rejection is dead-lettered;
- every ``send`` runs under the sink's deadline, so a hung sink costs that sink a timeout and
  a retry, never another sink or the ingest path (``offer`` is synchronous and O(1));
- a sink bug (an exception that is neither a ``SinkError`` nor the network's) is retried
  ``ERROR_ATTEMPTS`` times, then the batch is tried event by event and only the events that
  still fail are given up on, so one poisoned event cannot block the queue;
- a sink's background work (its optional ``run`` lifetime) runs in this runner's task group,
  between ``open`` and ``aclose``, never in a task group the sink holds itself.

The durable FIFO is a deque rather than a memory object stream because a failed batch must go
back to the *front*, in order, for the retry.
"""

from __future__ import annotations

import random
import time
from collections import deque
from typing import Any, cast

import anyio
import anyio.abc
import structlog

from gateway.c2.sink import LifetimeSink, Sink
from gateway.config import SinkEntry
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import LATEST_WINS_KINDS, Event, latest_key
from gateway.ops.instruments import Instruments
from gateway.ops.logsetup import RateLimit

__all__ = ["DEAD_LETTER_KEEP", "ERROR_ATTEMPTS", "MAX_LATEST_SLOTS", "SinkRunner"]

log = structlog.get_logger(__name__)

#: Dead-lettered events kept in memory for /status until the spool keeps them on disk.
DEAD_LETTER_KEEP = 1000
#: Latest-wins slots held for one sink at most (units reported over CoT, airframes ...).
MAX_LATEST_SLOTS = 10_000

#: Unexpected errors (sink bugs) in a row on one batch before its events are tried one by one
#: and those that still fail are given up on (dead-lettered, or counted if latest-wins).
ERROR_ATTEMPTS = 3
#: Backoff doublings at most: past this the delay is retry_max_s anyway, and 2**n stays small.
_MAX_DOUBLINGS = 32
_ERROR_LOG_INTERVAL_S = 30.0

_Item = tuple[Event, float]


def _is_transient(exc: BaseException) -> bool:
    """Worth retrying as it is: said so, a deadline, or the network (an untranslated OSError)."""
    return isinstance(exc, TransientSinkError | TimeoutError | OSError)


class _StartedFlag:
    """Forwards ``started()`` to the runner's task status and remembers that it was called."""

    def __init__(self, status: anyio.abc.TaskStatus[None]) -> None:
        self._status = status
        self.is_started = False

    def started(self, value: None = None) -> None:
        self.is_started = True
        self._status.started(value)


class SinkRunner:
    """Owns the queue of one sink and the task that feeds it."""

    def __init__(self, entry: SinkEntry, sink: Sink, instruments: Instruments) -> None:
        self.entry = entry
        self.sink = sink
        self.name = entry.name
        self.kinds = sink.kinds
        self._latest: dict[str, _Item] = {}
        self._durable: deque[_Item] = deque()
        self._wake = anyio.Event()
        self._waiting = False
        self._stopping = False
        self._done = anyio.Event()
        self._stop_requested = anyio.Event()
        self._lifetime_failure: BaseException | None = None
        self._error_attempts = 0
        self._needs_close = False
        self._error_log = RateLimit(interval_s=_ERROR_LOG_INTERVAL_S)
        self.dead_letters: deque[tuple[Event, str]] = deque(maxlen=DEAD_LETTER_KEEP)
        self.state = "starting"
        self.reason = ""
        self.failures_in_row = 0
        self.is_open = False
        self.close_timeout_s = entry.send_timeout_s
        inst = instruments
        self._sent = inst.sink_sent.labels(self.name)
        self._superseded = inst.sink_superseded.labels(self.name)
        self._overflow = inst.sink_dropped.labels(self.name, "overflow")
        self._rejected = inst.sink_dropped.labels(self.name, "rejected")
        self._given_up = inst.sink_dropped.labels(self.name, "error")
        self._latency = inst.sink_latency.labels(self.name)
        self._open_gauge = inst.sink_open.labels(self.name)
        self._failed = {
            reason: inst.sink_failed.labels(self.name, reason)
            for reason in ("transient", "timeout", "error", "permanent")
        }
        self._overflow_log = RateLimit(interval_s=5.0)
        self.log = log.bind(sink=self.name)

    @property
    def description(self) -> str:
        """How config errors name this runner's sink."""
        return f"sink {self.name!r} ({self.entry.type})"

    # -- ingest side: synchronous, O(1), never blocks ------------------------------------

    def offer(self, event: Event, ingest_mono: float) -> None:
        """Queue ``event`` by its kind's policy; wake the sender."""
        self.offer_slot(event, ingest_mono, latest_key(event))

    def offer_slot(self, event: Event, ingest_mono: float, slot: str | None) -> None:
        """``offer`` with the event's ``latest_key`` already computed (once, by the bus)."""
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
            latest[slot] = (event, ingest_mono)
        elif len(self._durable) >= self.entry.queue_max:
            self._overflow.inc()
            if self._overflow_log.allow("overflow"):
                self.log.error(
                    "sink_queue_overflowed",
                    kind=event.kind.value,
                    event_id=event.event_id,
                    queue_max=self.entry.queue_max,
                    note="durable events are being dropped until the sink catches up",
                )
            return
        else:
            self._durable.append((event, ingest_mono))
        if self._waiting:
            self._waiting = False
            self._wake.set()

    @property
    def depth(self) -> tuple[int, int]:
        """Events waiting: (latest-wins slots, durable)."""
        return len(self._latest), len(self._durable)

    def stop(self) -> None:
        """Ask the runner to finish: it drains what is queued, then closes the sink."""
        self._stopping = True
        self._stop_requested.set()
        self._waiting = False
        self._wake.set()

    async def wait_done(self) -> None:
        """Wait until ``run`` has returned."""
        await self._done.wait()

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
            if self._stopping and not any(self.depth):
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
            self.state, self.reason, self.failures_in_row = "open", "", 0
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
            self._waiting = False
            self._wake.set()

    async def _deliver_until_done(self) -> BaseException | None:
        while True:
            if self._lifetime_failure is not None:
                return self._lifetime_failure
            if not self._latest and not self._durable:
                if self._stopping:
                    return None
                self._wake = anyio.Event()
                self._waiting = True
                await self._wake.wait()
                continue
            await self._deliver(self._take())

    def _take(self) -> list[_Item]:
        limit = self.entry.batch_max
        items: list[_Item] = []
        if self._latest:
            if len(self._latest) <= limit:
                items.extend(self._latest.values())
                self._latest.clear()
            else:
                for key in list(self._latest)[:limit]:
                    items.append(self._latest.pop(key))
        while self._durable and len(items) < limit:
            items.append(self._durable.popleft())
        return items

    def _put_back(self, items: list[_Item]) -> None:
        durable = [item for item in items if item[0].kind not in LATEST_WINS_KINDS]
        self._durable.extendleft(reversed(durable))
        for item in items:
            slot = latest_key(item[0])
            if slot is not None:
                # A newer value that arrived during the failed send wins over the retry.
                self._latest.setdefault(slot, item)

    async def _send(self, items: list[_Item]) -> BaseException | None:
        """One ``send`` under the deadline: None if delivered, else what it raised.

        Cancelled mid-send (shutdown), the events are put back: the batch is still ours.
        """
        settled = False
        try:
            with anyio.fail_after(self.entry.send_timeout_s):
                await self.sink.send([event for event, _ in items])
            settled = True
        except Exception as exc:  # noqa: BLE001 - isolation boundary around one sink call
            settled = True
            return exc
        finally:
            if not settled:
                self._put_back(items)
        return None

    async def _deliver(self, items: list[_Item]) -> None:
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

    async def _deliver_one_by_one(self, items: list[_Item], failure: BaseException) -> None:
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

    def _delivered(self, items: list[_Item]) -> None:
        now = time.monotonic()
        observe = self._latency.observe
        for _, ingest_mono in items:
            observe(now - ingest_mono)
        self._sent.inc(len(items))
        if self.failures_in_row:
            self.log.info("sink_recovered", after_failures=self.failures_in_row)
            self.state, self.reason, self.failures_in_row = "open", "", 0

    def _refused(self, items: list[_Item], exc: PermanentSinkError) -> None:
        """Dead-letter what ``exc`` names (the whole batch if it names nothing)."""
        self._failed["permanent"].inc()
        if not exc.event_ids:
            self._dead_letter(items, str(exc))
            return
        refused = [item for item in items if item[0].event_id in exc.event_ids]
        self._dead_letter(refused, str(exc))
        self._delivered([item for item in items if item[0].event_id not in exc.event_ids])
        if strangers := len(exc.event_ids) - len(refused):
            self.log.warning("sink_refused_unknown_events", count=strangers)

    def _give_up(self, item: _Item, exc: BaseException) -> None:
        event = item[0]
        reason = f"sink error after {ERROR_ATTEMPTS} attempts: {type(exc).__name__}: {exc}"
        if event.kind in LATEST_WINS_KINDS:
            self._given_up.inc()  # superseded soon anyway; counted, not dead-lettered
        else:
            self.dead_letters.append((event, reason))
            self._rejected.inc()
        self.log.error(
            "sink_event_given_up", kind=event.kind.value, event_id=event.event_id, reason=reason
        )

    def _dead_letter(self, items: list[_Item], reason: str) -> None:
        for event, _ in items:
            if event.kind in LATEST_WINS_KINDS:
                continue
            self.dead_letters.append((event, reason))
            self._rejected.inc()
        self.log.error("sink_events_rejected", count=len(items), reason=reason)

    def retry_delay_s(self) -> float:
        """The backoff before the next attempt, before jitter, for ``failures_in_row``."""
        doublings = min(max(self.failures_in_row - 1, 0), _MAX_DOUBLINGS)
        return min(self.entry.retry_max_s, self.entry.retry_initial_s * 2.0**doublings)

    async def _backoff(self, step: str, exc: BaseException) -> None:
        if isinstance(exc, TimeoutError):
            reason, detail = "timeout", f"{step} exceeded {self.entry.send_timeout_s} s"
        elif _is_transient(exc):
            reason, detail = "transient", str(exc)
        else:
            reason, detail = "error", f"{type(exc).__name__}: {exc}"
        self._failed[reason].inc()
        self.failures_in_row += 1
        # Full jitter in [delay/2, delay] keeps many gateways from retrying in lock step.
        delay = self.retry_delay_s() * random.uniform(0.5, 1.0)  # noqa: S311 - not crypto
        self.state, self.reason = "retrying", detail
        fields: dict[str, Any] = {
            "step": step,
            "reason": reason,
            "detail": detail,
            "failures_in_row": self.failures_in_row,
            "retry_in_s": round(delay, 3),
        }
        if reason != "error":
            self.log.warning("sink_call_failed", **fields)
        elif self._error_log.allow(step):
            # A sink bug: the traceback once per interval, every occurrence counted.
            self.log.warning("sink_call_failed", exc_info=exc, **fields)
        if self._stopping:
            # Draining at shutdown: do not wait out a long backoff; the deadline decides.
            delay = min(delay, 0.1)
        with anyio.move_on_after(delay):
            await self._stop_requested.wait()

    def status(self) -> dict[str, object]:
        """The runner's state for /status."""
        latest, durable = self.depth
        return {
            "sink": self.name,
            "type": self.entry.type,
            "state": self.state,
            "reason": self.reason,
            "open": self.is_open,
            "failures_in_row": self.failures_in_row,
            "queued_latest": latest,
            "queued_durable": durable,
            "queue_max": self.entry.queue_max,
            "dead_letters": len(self.dead_letters),
            "sent": int(self._sent.value),
        }
