"""One sink's durable queue: a window in memory over what the spool owes the sink.

The spool (``gateway.spool.store``) holds every durable event until the sink confirms it; the
outbox keeps at most ``window`` of them in memory, in ``seq`` order. When more arrive than fit,
or at start-up (events owed from before a restart), the outbox is *spilled*: new events stay
in the spool only, and the window is refilled from it, in order, as the sink takes events.
An event leaves the spool only by ``confirm`` (delivered) or ``dead_letter`` (refused for good,
or expired by its kind's stale rule).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

from gateway.config import StaleRule
from gateway.events import Event, EventKind
from gateway.spool.store import Spool

__all__ = ["Outbox", "Queued"]


@dataclass(slots=True)
class Queued:
    """A durable event in a sink's window: its spool ``seq`` and when it was spooled."""

    event: Event
    ingest_mono: float
    seq: int
    spooled_at: float = field(default_factory=time.time)


class Outbox:
    """The durable queue of sink ``sink`` over ``spool``."""

    def __init__(
        self,
        sink: str,
        spool: Spool,
        *,
        window: int,
        stale: Mapping[EventKind, StaleRule] | None = None,
    ) -> None:
        self.sink = sink
        self.spool = spool
        self.window = window
        self.stale = dict(stale or {})
        self._items: deque[Queued] = deque()
        self._loaded_high = 0  # highest seq ever put in the window
        self._spilled = spool.pending_count(sink) > 0  # owed from before a restart

    def __len__(self) -> int:
        return len(self._items)

    @property
    def drained(self) -> bool:
        """True if nothing is in the window and nothing waits in the spool to refill it."""
        return not self._items and not self._spilled

    @property
    def owed(self) -> int:
        """Events the spool owes this sink (in the window, in flight, or only on disk)."""
        return self.spool.pending_count(self.sink)

    def append(self, event: Event, ingest_mono: float) -> bool:
        """Spool ``event`` for this sink alone and queue it; False if the spool is full."""
        seq = self.spool.append(event, (self.sink,))
        if seq is None:
            return False
        self.add(event, ingest_mono, seq)
        return True

    def add(self, event: Event, ingest_mono: float, seq: int) -> None:
        """Queue an event already in the spool for this sink (``seq``)."""
        if self._spilled or len(self._items) >= self.window:
            self._spilled = True  # it is in the spool; the refill brings it, in order
            return
        self._items.append(Queued(event, ingest_mono, seq))
        self._loaded_high = seq

    def refill(self) -> None:
        """Bring spilled events back into the window, in order, if the window is empty."""
        if self._items or not self._spilled:
            return
        rows = self.spool.pending(self.sink, after=self._loaded_high, limit=self.window)
        now_mono, now = time.monotonic(), time.time()
        for row in rows:
            ingest_mono = now_mono - max(now - row.spooled_at, 0.0)
            self._items.append(Queued(row.event, ingest_mono, row.seq, row.spooled_at))
            self._loaded_high = row.seq
        if len(rows) < self.window:
            self._spilled = False

    def poll(self) -> None:
        """Look for events put in the spool by someone else (a re-queue by the CLI)."""
        self.spool.take_requeued()
        self.spool.recount(self.sink)
        self._spilled = True
        self.refill()

    def take(self, limit: int) -> tuple[list[Queued], list[tuple[Queued, str]]]:
        """Up to ``limit`` events to send, and the stale ones that expired instead.

        An event older than its kind's stale rule is either marked ``late_by_s`` and sent, or
        returned as expired (with the reason) for the caller to dead-letter.
        """
        group = self.spool.open_group
        if group is not None and group.has_appends:
            self.spool.flush()  # nothing is sent before it is held; a failed group is skipped
        self.refill()
        taken: list[Queued] = []
        expired: list[tuple[Queued, str]] = []
        now = time.time()
        rolled_back = self.spool.rolled_back
        while self._items and len(taken) + len(expired) < limit:
            item = self._items.popleft()
            if item.seq in rolled_back:
                continue  # its batch never committed: not held, not ours to send
            rule = self.stale.get(item.event.kind)
            age = now - item.spooled_at
            if rule is not None and age > rule.after_s:
                if rule.action == "expire":
                    reason = f"expired: stale after {rule.after_s:g} s in the spool"
                    expired.append((item, reason))
                    continue
                if getattr(item.event, "late_by_s", None) is None:
                    item.event = item.event.model_copy(update={"late_by_s": round(age, 3)})
            taken.append(item)
            if not self._items:
                self.refill()
        return taken, expired

    def put_back(self, items: list[Queued]) -> None:
        """Return a batch that was not delivered to the front, in order."""
        self._items.extendleft(reversed(items))

    def confirm(self, items: list[Queued]) -> None:
        """The sink has these events: the spool no longer owes them."""
        self.spool.confirm(self.sink, [item.seq for item in items])

    def dead_letter(self, items: list[Queued], reason: str) -> None:
        """These events will never be delivered as they are: keep them as dead letters."""
        self.spool.dead_letter(self.sink, [item.seq for item in items], reason)
