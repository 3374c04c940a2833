"""Drives one sink: its queue, batching, retry with backoff, dead letters and metrics.

Every sink gets the same delivery behaviour from here, and holds none of its own:

- latest-wins kinds (telemetry, link state, blue force) sit in one slot per key, so a slow
  sink gets the freshest value instead of a backlog;
- durable kinds (detections, tracks, ...) sit in a bounded FIFO and are never dropped
  silently: an overflow is counted and logged loudly, a permanent rejection is dead-lettered;
- every ``send`` runs under the sink's deadline, so a hung sink costs that sink a timeout and
  a retry, never another sink or the ingest path (``offer`` is synchronous and O(1)).

The durable FIFO is a deque rather than a memory object stream because a failed batch must go
back to the *front*, in order, for the retry.
"""

from __future__ import annotations

import random
import time
from collections import deque
from typing import Any

import anyio
import structlog

from gateway.config import SinkEntry
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import LATEST_WINS_KINDS, Event, latest_key
from gateway.instruments import Instruments
from gateway.logsetup import RateLimit
from gateway.sink import Sink

__all__ = ["DEAD_LETTER_KEEP", "SinkRunner"]

log = structlog.get_logger(__name__)

#: Dead-lettered events kept in memory for /status until the spool keeps them on disk.
DEAD_LETTER_KEEP = 1000

_Item = tuple[Event, float]


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
        self._latency = inst.sink_latency.labels(self.name)
        self._open_gauge = inst.sink_open.labels(self.name)
        self._failed = {
            reason: inst.sink_failed.labels(self.name, reason)
            for reason in ("transient", "timeout", "error", "permanent")
        }
        self._overflow_log = RateLimit(interval_s=5.0)
        self.log = log.bind(sink=self.name)

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
        self._waiting = False
        self._wake.set()

    async def wait_done(self) -> None:
        """Wait until ``run`` has returned."""
        await self._done.wait()

    # -- delivery side -------------------------------------------------------------------

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Open the sink (retrying), deliver until stopped and drained, then close it."""
        task_status.started()
        try:
            await self._open()
            while True:
                if not self._latest and not self._durable:
                    if self._stopping:
                        break
                    self._wake = anyio.Event()
                    self._waiting = True
                    await self._wake.wait()
                    continue
                await self._deliver(self._take())
        finally:
            self.is_open = False
            self._open_gauge.set(0.0)
            self.state = "closed"
            with anyio.move_on_after(self.close_timeout_s, shield=True):
                try:
                    await self.sink.aclose()
                except Exception:
                    self.log.exception("sink_close_failed")
            self._done.set()

    async def _open(self) -> None:
        while True:
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
            return

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

    async def _deliver(self, items: list[_Item]) -> None:
        batch = [event for event, _ in items]
        settled = False
        try:
            with anyio.fail_after(self.entry.send_timeout_s):
                await self.sink.send(batch)
            settled = True
        except PermanentSinkError as exc:
            settled = True
            self._failed["permanent"].inc()
            self._dead_letter(items, str(exc))
            return
        except Exception as exc:  # noqa: BLE001 - isolation boundary around one sink call
            settled = True
            self._put_back(items)
            await self._backoff("send", exc)
            return
        finally:
            if not settled:
                # Cancelled mid-send (shutdown): the batch is still ours, keep it queued.
                self._put_back(items)
        now = time.monotonic()
        observe = self._latency.observe
        for _, ingest_mono in items:
            observe(now - ingest_mono)
        self._sent.inc(len(items))
        if self.failures_in_row:
            self.log.info("sink_recovered", after_failures=self.failures_in_row)
            self.state, self.reason, self.failures_in_row = "open", "", 0

    def _dead_letter(self, items: list[_Item], reason: str) -> None:
        for event, _ in items:
            if event.kind in LATEST_WINS_KINDS:
                continue
            self.dead_letters.append((event, reason))
            self._rejected.inc()
        self.log.error("sink_events_rejected", count=len(items), reason=reason)

    async def _backoff(self, step: str, exc: BaseException) -> None:
        if isinstance(exc, TimeoutError):
            reason, detail = "timeout", f"{step} exceeded {self.entry.send_timeout_s} s"
        elif isinstance(exc, TransientSinkError):
            reason, detail = "transient", str(exc)
        else:
            reason, detail = "error", f"{type(exc).__name__}: {exc}"
        self._failed[reason].inc()
        self.failures_in_row += 1
        delay = min(
            self.entry.retry_max_s, self.entry.retry_initial_s * 2 ** (self.failures_in_row - 1)
        )
        # Full jitter in [delay/2, delay] keeps many gateways from retrying in lock step.
        delay *= random.uniform(0.5, 1.0)  # noqa: S311 - jitter, not cryptography
        self.state, self.reason = "retrying", detail
        fields: dict[str, Any] = {
            "step": step,
            "reason": reason,
            "detail": detail,
            "failures_in_row": self.failures_in_row,
            "retry_in_s": round(delay, 3),
        }
        if reason == "error":
            self.log.warning("sink_call_failed", exc_info=exc, **fields)
        else:
            self.log.warning("sink_call_failed", **fields)
        if self._stopping:
            # Draining at shutdown: do not wait out a long backoff; the deadline decides.
            delay = min(delay, 0.1)
        await anyio.sleep(delay)

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
