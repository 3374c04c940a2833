"""What the Ra 180 sink sends, when: a byte budget per minute and a priority, with no I/O.

``Budget.offer(track, now)`` decides what a Track is worth on the net and holds its message;
``Budget.next_due(now)`` gives the message to send now, if the budget allows one;
``Budget.sent(item, now)`` records that it went. Time is a monotonic float passed in, so a
test drives it with any clock.

**Priority.** A hostile track the net has not heard of yet (``NEW``) goes before an update
of one it has (``UPDATE``); within a priority, hostile before suspect before unknown, then
oldest first. An update is worth sending only when the track moved at least
``min_move_m`` from the position last sent, or changed class or hostility; otherwise it is
a repeat and suppressed. A lost track's held message is dropped.

**Latest wins.** At most one message per track is held: a newer one replaces it (keeping
its place in line, so a track updated every second is not starved), so what is held is
bounded by the number of tracks, itself capped at ``max_tracks``: a new track takes the
place of the least recently heard one with nothing held; when every track holds a message,
the least important message gives way, unless the newcomer's would matter less still.

**Budget.** A token bucket of ``burst_bytes`` refilled at ``(bytes_per_minute -
burst_bytes) / 60`` bytes a second, starting full. In any 60 s window at most the bucket's
content plus a minute's refill go out, so never more than ``bytes_per_minute``.
"""

from __future__ import annotations

import contextlib
import heapq
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum

from gateway.domain.geodesy import distance_bearing
from gateway.events import Track
from sinks.ra180.cdm import Cdm, CdmError, MessageType

__all__ = ["Budget", "BudgetCounts", "Encode", "Outgoing", "Priority", "TokenBucket"]

Encode = Callable[[Track, MessageType, int], tuple[Cdm, bytes]]
"""``encode(track, message_type, number) -> (cdm, frame)``; raises ``CdmError``."""

_RANK = {"hostile": 0, "suspect": 1, "unknown": 2}


class Priority(IntEnum):
    """Lower goes first."""

    NEW = 0
    UPDATE = 1


class TokenBucket:
    """Bytes allowed on the net: ``capacity`` at most, refilled at ``rate_bps`` a second."""

    def __init__(self, capacity: float, rate_bps: float, now: float | None = None) -> None:
        self.capacity = capacity
        self.rate_bps = rate_bps
        self.tokens = capacity
        self._updated = now  # None: full until first used

    def _refill(self, now: float) -> None:
        if self._updated is None:
            self._updated = now
        elif now > self._updated:
            self.tokens = min(self.capacity, self.tokens + (now - self._updated) * self.rate_bps)
            self._updated = now

    def wait_s(self, size: int, now: float) -> float:
        """Seconds until ``size`` bytes may go (0: now)."""
        self._refill(now)
        missing = size - self.tokens
        # A millionth of a byte short is rounding from the refill, not a reason to wait
        # (a wait that small would not move a float clock forward).
        return 0.0 if missing <= 1e-6 else missing / self.rate_bps

    def spend(self, size: int, now: float) -> None:
        """Take ``size`` bytes (the caller checked ``wait_s`` is 0)."""
        self._refill(now)
        self.tokens -= size


@dataclass(slots=True)
class Outgoing:
    """One message held for the net, or being sent."""

    track_id: str
    number: int
    priority: Priority
    rank: int
    seq: int
    cdm: Cdm
    frame: bytes
    lat_deg: float
    lon_deg: float
    object_class: str
    hostility: str
    track: Track
    has_waited: bool = False

    def order(self) -> tuple[int, int, int]:
        """The sort key: priority, then hostility, then age."""
        return (self.priority, self.rank, self.seq)


@dataclass(slots=True)
class _Known:
    number: int
    heard: int  # when last offered, in offers: the lower, the longer ago
    sent: tuple[float, float, str, str] | None = None  # lat, lon, class, hostility last sent


@dataclass(slots=True)
class BudgetCounts:
    """What the budget did with what it was offered (all monotonic but ``held``)."""

    offered: int = 0
    not_reported: int = 0
    unencodable: int = 0
    suppressed: int = 0
    superseded: int = 0
    held_back: int = 0
    dropped_full: int = 0
    dropped_lost: int = 0
    sent: int = 0
    sent_new: int = 0
    sent_update: int = 0
    bytes_sent: int = 0


class Budget:
    """The Ra 180 sink's held messages, their priority and the byte budget."""

    def __init__(
        self,
        encode: Encode,
        *,
        bytes_per_minute: int,
        burst_bytes: int,
        min_move_m: float,
        max_tracks: int,
        report: frozenset[str],
        now: float | None = None,
    ) -> None:
        if bytes_per_minute <= burst_bytes:
            raise ValueError("bytes_per_minute must be more than burst_bytes")
        self._encode = encode
        self.bucket = TokenBucket(burst_bytes, (bytes_per_minute - burst_bytes) / 60.0, now)
        self.min_move_m = min_move_m
        self.max_tracks = max_tracks
        self.report = report
        self.counts = BudgetCounts()
        self._known: OrderedDict[str, _Known] = OrderedDict()
        self._held: dict[str, Outgoing] = {}
        self._line: list[tuple[int, int, int, int, Outgoing]] = []
        # The same held messages, least important first (a max-heap by negated order), and
        # the tracks with nothing held, least recently heard first: a new track makes room
        # in O(log n) even when every one of ``max_tracks`` tracks holds a message. Both are
        # lazy: entries of sent, replaced, re-heard or forgotten tracks are skipped.
        self._worst: list[tuple[int, int, int, int, Outgoing]] = []
        self._idle: list[tuple[int, str]] = []
        self._heard = 0
        self._pushes = 0
        self._seq = 0
        self._next_number = 1

    @property
    def held(self) -> int:
        """Messages waiting for the budget or the radio now."""
        return len(self._held)

    def _number(self) -> int:
        number = self._next_number
        self._next_number = number % 9999 + 1  # 0001..9999, then round again
        return number

    def offer(self, track: Track) -> str:
        """Take ``track`` in; returns what became of it (a ``BudgetCounts`` field name).

        ``"held"`` when a message now waits for the net. Raises ``CdmError`` (after counting
        it) when the track cannot be written as a CDM (a polar position).
        """
        c = self.counts
        c.offered += 1
        if track.status in ("lost", "merged"):
            # Gone, or folded into another track the net keeps hearing: its wait ends here.
            self._known.pop(track.track_id, None)
            if self._drop_held(track.track_id) is not None:
                c.dropped_lost += 1
                return "dropped_lost"
            return "not_reported"
        if track.hostility not in self.report:
            c.not_reported += 1
            # No longer what the net hears (say hostile → suspect): its waiting message goes.
            if self._drop_held(track.track_id) is not None:
                c.superseded += 1
            return "not_reported"
        return self._place(track)

    def _place(self, track: Track) -> str:
        c = self.counts
        known = self._remember(track)
        if known is None:
            c.dropped_full += 1
            return "dropped_full"
        position = (track.position.lat_deg, track.position.lon_deg)
        priority = Priority.NEW if known.sent is None else Priority.UPDATE
        if known.sent is not None:
            lat, lon, cls, hostility = known.sent
            moved_m = distance_bearing(lat, lon, *position)[0]
            if moved_m < self.min_move_m and (cls, hostility) == (
                track.object_class,
                track.hostility,
            ):
                c.suppressed += 1
                if self._drop_held(track.track_id) is not None:
                    c.superseded += 1  # a held update the track has since come back from
                return "suppressed"
        message_type: MessageType = "MAL" if priority is Priority.NEW else "UPPD"
        try:
            cdm, frame = self._encode(track, message_type, known.number)
        except CdmError:
            c.unencodable += 1
            raise
        previous = self._held.get(track.track_id)
        if previous is not None:
            c.superseded += 1
            seq, waited = previous.seq, previous.has_waited
        else:
            self._seq += 1
            seq, waited = self._seq, False
        item = Outgoing(
            track.track_id,
            known.number,
            priority,
            _RANK.get(track.hostility, len(_RANK)),
            seq,
            cdm,
            frame,
            *position,
            track.object_class,
            track.hostility,
            track,
            waited,
        )
        self._hold(item)
        return "held"

    def _remember(self, track: Track) -> _Known | None:
        """The track's state, made room for if new; None if every slot matters more."""
        self._heard += 1
        known = self._known.get(track.track_id)
        if known is not None:
            self._known.move_to_end(track.track_id)
            known.heard = self._heard
        else:
            if len(self._known) >= self.max_tracks and not self._forget_one(track):
                return None
            known = self._known[track.track_id] = _Known(self._number(), self._heard)
        if track.track_id not in self._held:
            self._push_idle(track.track_id, known)
        return known

    def _push_idle(self, track_id: str, known: _Known) -> None:
        heapq.heappush(self._idle, (known.heard, track_id))
        if len(self._idle) > 2 * len(self._known) + 64:  # keep the stale entries bounded
            self._idle = [(k.heard, tid) for tid, k in self._known.items() if tid not in self._held]
            heapq.heapify(self._idle)

    def _drop_held(self, track_id: str) -> Outgoing | None:
        """Take ``track_id``'s held message away; the track, if still known, is idle now."""
        item = self._held.pop(track_id, None)
        known = self._known.get(track_id)
        if item is not None and known is not None:
            self._push_idle(track_id, known)
        return item

    def _forget_one(self, track: Track) -> bool:
        # The least recently heard track with nothing waiting costs only the net's memory of
        # it (its next update is announced as new); only if every track has a message
        # waiting does the least important message give way, unless the newcomer's would
        # be less important still.
        while self._idle:
            heard, track_id = heapq.heappop(self._idle)
            known = self._known.get(track_id)
            if known is not None and known.heard == heard and track_id not in self._held:
                del self._known[track_id]
                return True
        worst = self._least_important()
        if worst is None:
            return False  # max_tracks known and none idle or held: cannot happen
        if (Priority.NEW, _RANK.get(track.hostility, len(_RANK))) > worst.order()[:2]:
            return False
        del self._held[worst.track_id]
        del self._known[worst.track_id]
        self.counts.dropped_full += 1
        return True

    def _least_important(self) -> Outgoing | None:
        while self._worst:
            item = self._worst[0][-1]
            if self._held.get(item.track_id) is item:
                return item
            heapq.heappop(self._worst)
        return None

    def _hold(self, item: Outgoing) -> None:
        """Put ``item`` in the line (a heap; entries of replaced or sent items are skipped)."""
        self._held[item.track_id] = item
        self._pushes += 1
        heapq.heappush(self._line, (*item.order(), self._pushes, item))
        priority, rank, seq = item.order()
        heapq.heappush(self._worst, (-priority, -rank, -seq, -self._pushes, item))
        if len(self._line) > 2 * len(self._held) + 64:  # keep the stale entries bounded
            self._line = [e for e in self._line if self._held.get(e[-1].track_id) is e[-1]]
            heapq.heapify(self._line)
        if len(self._worst) > 2 * len(self._held) + 64:
            self._worst = [e for e in self._worst if self._held.get(e[-1].track_id) is e[-1]]
            heapq.heapify(self._worst)

    def _head(self) -> Outgoing | None:
        while self._line:
            item = self._line[0][-1]
            if self._held.get(item.track_id) is item:
                return item
            heapq.heappop(self._line)
        return None

    def next_due(self, now: float) -> Outgoing | None:
        """The message to send now, or None (nothing held, or the budget is spent).

        The message stays held until ``sent``; a message the budget made wait is counted
        in ``held_back`` once.
        """
        head = self._head()
        if head is None:
            return None
        if self.bucket.wait_s(len(head.frame), now) > 0:
            if not head.has_waited:
                head.has_waited = True
                self.counts.held_back += 1
            return None
        return head

    def wait_s(self, now: float) -> float | None:
        """Seconds until the next message may go; None when nothing is held."""
        head = self._head()
        return None if head is None else self.bucket.wait_s(len(head.frame), now)

    def sent(self, item: Outgoing, now: float) -> None:
        """``item`` went out whole: spend its bytes and remember what the net now knows."""
        self.bucket.spend(len(item.frame), now)
        known = self._known.get(item.track_id)
        if known is not None:
            known.sent = (item.lat_deg, item.lon_deg, item.object_class, item.hostility)
        newer = self._drop_held(item.track_id)
        if newer is not None and newer is not item:
            # Offered while this one was on its way: weigh it again against what the net now
            # knows (a new target's second message is an update, or a repeat).
            with contextlib.suppress(CdmError):  # encoded once already; counted if not now
                self._place(newer.track)
        c = self.counts
        c.sent += 1
        c.bytes_sent += len(item.frame)
        if item.priority is Priority.NEW:
            c.sent_new += 1
        else:
            c.sent_update += 1
