"""The local order source: an operator's orders from ``fischer-gateway order`` on this node.

Listens on a Unix socket (``socket``, created with mode ``socket_mode``, 0600 by default).
The socket's file permissions and the peer's credentials are the authentication: a
connection is served only if the kernel reports (SO_PEERCRED) a peer uid that is the
daemon's own, root's, or one of ``allowed_uids``; anything else is closed unanswered and
counted ``refused_peer``.

One order per connection, as one line of JSON in SLB's order format
(``sinks.slb.order``, schema ``slb-order.schema.json``; ``fischer-gateway order``
writes it), at most ``max_line_bytes``, within ``timeout_s``. The answer is JSON lines:
``{"order_id": .., "status": "received", "event_id": "local-order-<order_id>"}`` once the
order is held durably (``{"status": "rejected", "reason": ..}`` for a malformed one,
``{"status": "not_held"}`` if the spool refused it), then each ``OrderStatus`` of the order
from the orders processor as it comes (``status``, ``check``, ``reason``, ``airframe``),
until a final one (``rejected``, ``completed``, ``failed``) or the client hangs up. Each
status line carries the order's status ``seq``: statuses are sent at least once, and a
reader drops one whose ``seq`` it has. A line ``{"status_of": ORDER_ID}`` (``fischer-gateway
order --status ORDER_ID``) is answered with every status the daemon keeps for that order of
this source, in ``seq`` order, from the spool's order book (kept across restarts, for a
client that was gone when they came), then the connection closes; ``{"status": "unknown"}``
if none is kept. An
order id already taken is answered ``rejected`` (the same order again) or ``conflict`` (with
other content: the first order stands). At most
``max_connections`` connections are served at once; more are closed at once, counted.
"""

from __future__ import annotations

import json
import os
import socket
import struct
from collections import Counter, OrderedDict
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any, ClassVar

import anyio
import anyio.abc
import structlog
from anyio.streams.buffered import BufferedByteReceiveStream
from anyio.streams.memory import MemoryObjectSendStream
from pydantic import Field

from gateway.c2.source import SourceConfig, StatusArchive
from gateway.clock import utc_now
from gateway.errors import OrderRejected
from gateway.events import Event, OrderState, OrderStatus
from gateway.ops.logsetup import RateLimit
from sinks.slb.order import read_order

__all__ = ["LocalOrderSource", "LocalOrderSourceConfig"]

log = structlog.get_logger(__name__)

EVENT_ID_PREFIX = "local-order-"
_FINAL = frozenset(
    {OrderState.REJECTED, OrderState.CONFLICT, OrderState.COMPLETED, OrderState.FAILED}
)
_WATCH_QUEUE = 32
#: Order ids taken, remembered so a second order with one of them is refused, not lost.
_REMEMBERED_IDS = 10_000
_MAX_ORDER_ID = 128


class LocalOrderSourceConfig(SourceConfig):
    """Options of the local order source (beside ``name`` and ``type: local``)."""

    socket: Path = Field(
        description="The Unix socket to listen on, e.g. /var/lib/fischer-gateway/orders.sock."
    )
    socket_mode: int = Field(
        default=0o600, ge=0, le=0o777, description="Its file mode: 0600 (owner), 0660 (group)."
    )
    allowed_uids: tuple[int, ...] = Field(
        default=(), description="Peer uids served besides the daemon's own and root's."
    )
    max_connections: int = Field(default=8, ge=1, le=256, description="Served at once.")
    max_line_bytes: int = Field(
        default=65536, ge=1024, le=1 << 20, description="Largest order line read."
    )
    timeout_s: float = Field(
        default=5.0, gt=0, le=300, description="Deadline to read the order line."
    )


def _peer_uid(stream: anyio.abc.SocketStream) -> int | None:
    raw = stream.extra(anyio.abc.SocketAttribute.raw_socket)
    try:
        creds = raw.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    except (OSError, AttributeError):
        return None
    _pid, uid, _gid = struct.unpack("3i", creds)
    return int(uid)


class LocalOrderSource:
    """Takes an operator's orders on a Unix socket and streams their statuses back."""

    config_model: ClassVar[type[LocalOrderSourceConfig]] = LocalOrderSourceConfig

    def __init__(
        self,
        name: str,
        config: LocalOrderSourceConfig,
        publish: Callable[[Event], bool],
        *,
        clock: Callable[[], datetime] = utc_now,
    ) -> None:
        self.name = name
        self.config = config
        self._publish = publish
        self._clock = clock
        self._uids = frozenset({os.getuid(), 0, *config.allowed_uids})
        self._watchers: dict[str, set[MemoryObjectSendStream[OrderStatus]]] = {}
        #: Order event ids taken, with the digest of each order's content.
        self._taken: OrderedDict[str, str] = OrderedDict()
        self._active = 0
        self._archive: StatusArchive | None = None
        self.counts: Counter[str] = Counter()
        self._log_limit = RateLimit(interval_s=10.0)
        self.log = log.bind(source=name, socket=str(config.socket))

    def status(self) -> dict[str, object]:
        """What /status shows for this source."""
        return {
            "source": self.name,
            "type": "local",
            "socket": str(self.config.socket),
            "connections": self._active,
            "counts": dict(self.counts),
        }

    def keep_statuses(self, archive: StatusArchive) -> None:
        """Answer ``status_of`` questions from ``archive`` (the assembly hands it over)."""
        self._archive = archive

    def on_order_status(self, status: OrderStatus) -> None:
        """Pass a status of one of this source's orders to the connections waiting for it."""
        if status.source != self.name:
            return
        for watcher in list(self._watchers.get(status.order_event_id, ())):
            try:
                watcher.send_nowait(status)
            except (anyio.WouldBlock, anyio.ClosedResourceError, anyio.BrokenResourceError):
                self.counts["status_dropped"] += 1

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind the socket (replacing a stale one), report started, serve until cancelled."""
        path = self.config.socket
        if path.is_socket():
            path.unlink()  # left by a daemon that did not stop cleanly
        listener = await anyio.create_unix_listener(path)
        try:
            path.chmod(self.config.socket_mode)
            task_status.started()
            await listener.serve(self._serve)
        finally:
            path.unlink(missing_ok=True)  # before the await: a cancelled close ends here
            await listener.aclose()

    def _count(self, outcome: str, **fields: object) -> None:
        self.counts[outcome] += 1
        if self._log_limit.allow(outcome):
            self.log.warning("local_order_problem", outcome=outcome, **fields)

    async def _serve(self, stream: anyio.abc.SocketStream) -> None:
        async with stream:
            if self._active >= self.config.max_connections:
                self._count("too_many_connections")
                return
            uid = _peer_uid(stream)
            if uid is None or uid not in self._uids:
                self._count("refused_peer", uid=uid)
                return
            self._active += 1
            try:
                await self._order(stream)
            except (anyio.BrokenResourceError, anyio.ClosedResourceError, anyio.EndOfStream):
                self.counts["client_gone"] += 1
            finally:
                self._active -= 1

    async def _order(self, stream: anyio.abc.SocketStream) -> None:
        reader = BufferedByteReceiveStream(stream)
        try:
            with anyio.fail_after(self.config.timeout_s):
                line = await reader.receive_until(b"\n", self.config.max_line_bytes)
        except anyio.DelimiterNotFound:
            self._count("oversize")
            limit = self.config.max_line_bytes
            reason = f"order: no end of line within max_line_bytes ({limit})"
            await _say(stream, {"status": "rejected", "reason": reason})
            return
        except (TimeoutError, anyio.IncompleteRead):
            self._count("no_order_line")
            await _say(stream, {"status": "rejected", "reason": "order: no JSON line received"})
            return
        try:
            element: Any = json.loads(line, parse_constant=_no_constant)
        except _NotJson as exc:
            self._count("malformed")
            await _say(stream, {"status": "rejected", "reason": f"order: {exc}"})
            return
        except (ValueError, RecursionError):
            self._count("malformed")
            await _say(stream, {"status": "rejected", "reason": "order: not JSON"})
            return
        if isinstance(element, dict) and set(element) == {"status_of"}:
            await self._status_of(stream, element["status_of"])
            return
        try:
            parsed = read_order(element, source=self.name)
        except OrderRejected as exc:
            self._count("rejected", reason=str(exc))
            order_id = element.get("order_id") if isinstance(element, dict) else None
            await _say(stream, {"order_id": order_id, "status": "rejected", "reason": str(exc)})
            return
        order = parsed.model_copy(update={"event_id": EVENT_ID_PREFIX + parsed.order_id})
        digest = order.content_digest()
        taken = self._taken.get(order.event_id)
        if taken is not None and taken != digest:
            # The same order id with other content: a conflict, the first order stands.
            self._count("conflict", order_id=order.order_id)
            reason = (
                f"order_id: {order.order_id} was already taken with other content; the first"
                " stands: give a changed order a new id"
            )
            await _say(stream, {"order_id": order.order_id, "status": "conflict", "reason": reason})
            return
        if taken is None and self._archive is not None and self._archive.statuses(order.event_id):
            taken = digest  # taken before the daemon restarted: its statuses are kept
        if taken is not None or order.event_id in self._watchers:
            # The orders processor answers each order id once: a second order with it
            # would wait for statuses that never come.
            self._count("duplicate_order_id", order_id=order.order_id)
            reason = (
                f"order_id: {order.order_id} was already taken; give a new order id"
                f" (fischer-gateway order --status {order.order_id} shows its statuses)"
            )
            await _say(stream, {"order_id": order.order_id, "status": "rejected", "reason": reason})
            return
        send, receive = anyio.create_memory_object_stream[OrderStatus](_WATCH_QUEUE)
        watchers = self._watchers.setdefault(order.event_id, set())
        watchers.add(send)
        try:
            if not self._publish(order):
                self._count("not_held", order_id=order.order_id)
                await _say(stream, {"order_id": order.order_id, "status": "not_held"})
                return
            self.counts["received"] += 1
            self._taken[order.event_id] = digest
            while len(self._taken) > _REMEMBERED_IDS:
                self._taken.popitem(last=False)
            self.log.info("local_order_received", order_id=order.order_id, task=order.task.value)
            await _say(
                stream,
                {"order_id": order.order_id, "status": "received", "event_id": order.event_id},
            )
            async with anyio.create_task_group() as tg:
                # A client that hangs up (the command without --follow, once accepted) frees
                # its connection now, not at the order's next status, which may never come.
                tg.start_soon(_until_hangup, stream, tg.cancel_scope)
                async for status in receive:
                    try:
                        await _say(stream, _line(status))
                    except (anyio.BrokenResourceError, anyio.ClosedResourceError):
                        # Hung up before the hang-up was seen: inside the task group this
                        # would leave as an exception group, past _serve, ending the source.
                        self.counts["client_gone"] += 1
                        tg.cancel_scope.cancel()
                        break
                    if status.status in _FINAL:
                        tg.cancel_scope.cancel()
                        break
        finally:
            watchers.discard(send)
            if not watchers:
                self._watchers.pop(order.event_id, None)
            send.close()
            receive.close()

    async def _status_of(self, stream: anyio.abc.SocketStream, order_id: object) -> None:
        """Answer every status kept for one of this source's orders (module docstring)."""
        if not isinstance(order_id, str) or not 0 < len(order_id) <= _MAX_ORDER_ID:
            self._count("malformed")
            await _say(stream, {"status": "rejected", "reason": "status_of: not an order id"})
            return
        self.counts["status_of"] += 1
        kept = [] if self._archive is None else self._archive.statuses(EVENT_ID_PREFIX + order_id)
        if not kept:
            reason = "no statuses are kept for this order id"
            await _say(stream, {"order_id": order_id, "status": "unknown", "reason": reason})
            return
        for status in kept:
            await _say(stream, _line(status))


class _NotJson(ValueError):
    """A constant JSON does not have (NaN, Infinity), as SLB's reader refuses it too."""


def _no_constant(name: str) -> Any:
    raise _NotJson(f"{name} is not JSON")


def _line(status: OrderStatus) -> dict[str, Any]:
    return {
        "order_id": status.order_id,
        "status": status.status.value,
        "airframe": status.airframe,
        "check": status.check,
        "reason": status.reason,
        "event_id": status.event_id,
        "seq": status.seq,
    }


async def _until_hangup(stream: anyio.abc.SocketStream, scope: anyio.CancelScope) -> None:
    """Drop whatever the client sends until it hangs up, then cancel ``scope``.

    Waits on the raw socket with ``anyio.wait_readable``: cancelling a pending
    ``stream.receive`` as the client closes makes the event loop log an InvalidStateError.
    """
    raw = stream.extra(anyio.abc.SocketAttribute.raw_socket)
    while True:
        try:
            await anyio.wait_readable(raw)
            data = raw.recv(4096, socket.MSG_DONTWAIT)
        except BlockingIOError:
            continue
        except (OSError, anyio.ClosedResourceError):
            break
        if not data:
            break
    scope.cancel()


async def _say(stream: anyio.abc.SocketStream, line: dict[str, Any]) -> None:
    await stream.send(json.dumps(line).encode() + b"\n")
