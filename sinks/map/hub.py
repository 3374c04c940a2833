"""The change stream's fan-out: each subscriber a bounded queue of encoded messages.

``Hub.publish`` numbers each change (``seq``), encodes it once as an SSE message and offers it
to every subscriber whose layers it touches, without waiting: a subscriber whose queue is full
(a browser that stopped reading) is cut off, and its stream ends with an ``overflow`` event so
the client reconnects and starts again from a snapshot. Nothing here grows without bound.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterable
from typing import Any

__all__ = ["CLOSED", "Hub", "Subscription", "sse"]

#: What a subscription's queue yields after the hub closes it: the stream ends.
CLOSED = b""


def sse(event: str, data: Any, seq: int | None = None) -> bytes:
    """One Server-Sent Events message: ``event``, ``id`` (when given) and one ``data`` line."""
    text = json.dumps(data, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    head = f"event: {event}\n" + ("" if seq is None else f"id: {seq}\n")
    return f"{head}data: {text}\n\n".encode()


class Subscription:
    """One client's stream: encoded messages of its ``layers``, oldest first."""

    def __init__(self, layers: frozenset[str], queue_max: int) -> None:
        self.layers = layers
        self.queue: asyncio.Queue[bytes] = asyncio.Queue(maxsize=queue_max)
        self.overflowed = False

    def offer(self, message: bytes) -> bool:
        """Queue ``message``; False (and the subscription ended) when the queue is full."""
        try:
            self.queue.put_nowait(message)
        except asyncio.QueueFull:
            self.overflowed = True
            self._end()
            return False
        return True

    def _end(self) -> None:
        # Make room for the end marker: the stream ends after what was queued before it.
        while self.queue.full():
            self.queue.get_nowait()
        self.queue.put_nowait(CLOSED)


class Hub:
    """Numbers changes and hands them to the subscribers."""

    def __init__(self, *, queue_max: int, seq: int = 0) -> None:
        self.queue_max = queue_max
        self.seq = seq
        self.published = 0
        self.cut_off = 0
        self._subscribers: set[Subscription] = set()
        self._closed = False

    @property
    def subscribers(self) -> int:
        """How many streams are open."""
        return len(self._subscribers)

    def subscribe(self, layers: Iterable[str]) -> Subscription:
        """A new subscription to ``layers`` (it sees changes from the next ``seq`` on)."""
        sub = Subscription(frozenset(layers), self.queue_max)
        if self._closed:
            sub._end()
        else:
            self._subscribers.add(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        """Forget ``sub`` (its client went away)."""
        self._subscribers.discard(sub)

    def publish(self, changes: Iterable[dict[str, Any]]) -> None:
        """Number, encode and offer each change; never waits."""
        for change in changes:
            self.seq += 1
            self.published += 1
            layer = change["layer"]
            wanting = [sub for sub in self._subscribers if layer in sub.layers]
            if not wanting:
                continue  # encoded only when someone reads it
            message = sse("change", {"seq": self.seq, **change}, self.seq)
            for sub in wanting:
                if not sub.offer(message):
                    self._subscribers.discard(sub)
                    self.cut_off += 1

    def close(self) -> None:
        """End every stream (the sink is closing); later subscriptions end at once."""
        self._closed = True
        for sub in self._subscribers:
            sub._end()
        self._subscribers.clear()
