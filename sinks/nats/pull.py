"""Reading a durable pull consumer: one pull request at a time, each on its own reply subject.

Why not nats-py's ``fetch(batch)``: a pull request that expires ends with a ``408`` status,
and when that status arrives just after the client's own deadline the next ``fetch`` reads it
as the answer to its first request, then asks for a full batch *without* ``no_wait`` and
waits until the whole batch has come or the deadline passed. At 10 % load (``bench/nats.py``)
the first events after an idle second waited ``batch / rate`` (210 ms measured: the p99);
at a brigade's usual rates they would wait up to the fetch timeout.

Here every pull request has its own reply subject (``<inbox>.<n>``): a status that ends an
earlier request is recognised by it and ignored, and messages an earlier request delivers
late are still taken. A request asks ``no_wait`` with ``expires``: the server holds it until
a message is there, sends what is pending (at most ``batch``) and ends it at once, so an
event is handed on as soon as it arrives. The next request goes out as soon as the previous
one ended and fewer than ``batch`` messages wait here: messages flow in while the source
processes the previous batch. At most two batches wait here.
"""

from __future__ import annotations

import asyncio
import json
from collections import deque

import anyio
import structlog
from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.aio.subscription import Subscription

from gateway.errors import GatewayError

__all__ = ["PullFailed", "Puller"]

log = structlog.get_logger(__name__)

#: Status codes that end a pull request (no messages, request timeout, conflicts such as
#: "Exceeded MaxWaiting" or a leadership change): the next request is sent.
_ENDS = frozenset({"404", "408", "409"})
#: An idle heartbeat; nothing to do.
_HEARTBEAT = "100"


class PullFailed(GatewayError):
    """The server refused pulling the consumer (deleted, no JetStream): connect again."""


class Puller:
    """Pulls ``durable`` of ``stream`` into a bounded buffer; ``next_batch`` takes from it."""

    def __init__(
        self, nc: Client, stream: str, durable: str, *, batch: int, wait_s: float = 1.0
    ) -> None:
        self._nc = nc
        self._next_subject = f"$JS.API.CONSUMER.MSG.NEXT.{stream}.{durable}"
        self._inbox = nc.new_inbox()
        self.batch = batch
        self.wait_s = wait_s
        self._request = json.dumps(
            {"batch": batch, "expires": int(wait_s * 1e9), "no_wait": True}
        ).encode()
        self._buffer: deque[Msg] = deque()
        self._ready = asyncio.Event()  # messages wait in the buffer
        self._room = asyncio.Event()  # fewer than ``batch`` wait: ask for more
        self._room.set()
        self._ended = asyncio.Event()  # the open request ended
        self._open = ""  # reply token of the open request
        self._owed = 0  # messages the open request may still deliver
        self._count = 0
        self._subscription: Subscription | None = None
        self._failure: str | None = None
        #: Pull requests sent, and ended by a status (for /status and tests).
        self.requests = 0
        self.conflicts = 0

    async def run(self) -> None:
        """Subscribe, then keep one pull request out while the buffer has room, until cancelled."""
        self._subscription = await self._nc.subscribe(
            f"{self._inbox}.*",
            cb=self._on_message,
            pending_msgs_limit=self.batch * 4 + 64,
            pending_bytes_limit=0,  # bounded by the requests: at most two batches out
        )
        try:
            while True:
                await self._room.wait()
                self._count += 1
                self._open, self._owed = str(self._count), self.batch
                self._ended.clear()
                self.requests += 1
                await self._nc.publish(
                    self._next_subject, self._request, reply=f"{self._inbox}.{self._open}"
                )
                # The server ends the request by its expiry; a lost end (a reconnect) costs
                # one more wait, never a stall.
                with anyio.move_on_after(self.wait_s * 2 + 1.0):
                    await self._ended.wait()
                if self._failure is not None:
                    raise PullFailed(f"pulling {self._next_subject}: {self._failure}")
        finally:
            self._open = ""
            subscription, self._subscription = self._subscription, None
            if subscription is not None:
                with anyio.CancelScope(shield=True), anyio.move_on_after(1.0):
                    try:
                        await subscription.unsubscribe()
                    except Exception as exc:  # noqa: BLE001 - a closed connection: nothing to undo
                        log.debug("nats_unsubscribe_failed", error=str(exc)[:200])

    async def next_batch(self) -> list[Msg]:
        """The messages waiting (at most ``batch``), waiting for at least one."""
        while not self._buffer:
            self._ready.clear()
            await self._ready.wait()
        count = min(self.batch, len(self._buffer))
        messages = [self._buffer.popleft() for _ in range(count)]
        if not self._buffer:
            self._ready.clear()
        if len(self._buffer) < self.batch:
            self._room.set()
        return messages

    async def _on_message(self, msg: Msg) -> None:
        status = msg.headers.get("Status") if msg.headers else None
        if status is None:
            if not msg.reply:
                return  # not a JetStream delivery: nothing to ack, nothing to take
            self._buffer.append(msg)
            self._ready.set()
            if len(self._buffer) >= self.batch:
                self._room.clear()
            # A delivery keeps its own subject, not the request's: it counts against the
            # open request (the server serves one request after the other; one that came
            # late from an abandoned request at worst ends this one early).
            self._owed -= 1
            if self._owed <= 0:
                self._ended.set()
            return
        if status == _HEARTBEAT:
            return
        if msg.subject.rpartition(".")[2] != self._open:
            return  # the end of an earlier request, come late
        description = msg.headers.get("Description", "") if msg.headers else ""
        if status not in _ENDS or "deleted" in description.lower():
            self._failure = f"{status} {description}"[:200]
        elif status == "409":
            self.conflicts += 1
        self._ended.set()
