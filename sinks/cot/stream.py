"""The CoT source's TCP side: a bounded listener for ATAK/WinTAK streams, and the splitter.

A stream is XML events back to back, split after each ``</event>`` (``cot.md`` §8). The
splitter resynchronises on the last ``<event`` (with its ``<?xml`` declaration) before each
end, so a stray fragment (a bare ``<detail>``, half an event after a reconnect) costs only
itself: it is counted, and the event after it still parses.

The listener (``gateway.transports.listener``) bounds what peers can hold: ``max_clients``
connections at once (a new one evicts the stalest client that has not yet sent a whole event, else
it is closed), ``idle_timeout_s`` of silence closes a connection, each connection buffers at most
``max_event_bytes``, and an accept error (EMFILE, ENOBUFS, ECONNABORTED) degrades this one source,
never the daemon.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Callable

import anyio
import anyio.abc
import structlog

from gateway.ops.logsetup import RateLimit
from gateway.transports.listener import Connection, TcpListener
from gateway.transports.xmlstream import RootSplitter

__all__ = ["CotStreamServer", "EventSplitter"]

log = structlog.get_logger(__name__)

_END = re.compile(rb"</event>")
_EVENT_START = re.compile(rb"<event[\s>/]")


class EventSplitter(RootSplitter):
    """Cuts a CoT XML stream into events, skipping (and counting) what is not one."""

    def __init__(self, max_event_bytes: int) -> None:
        super().__init__(_EVENT_START, _END, max_event_bytes)


class CotStreamServer:
    """Accepts TCP clients and feeds each complete event to ``handle``, within bounds."""

    def __init__(
        self,
        host: str,
        port: int,
        handle: Callable[[bytes], None],
        reject: Callable[[str], None],
        *,
        max_clients: int,
        max_event_bytes: int,
        idle_timeout_s: float,
        name: str,
    ) -> None:
        self.host, self.port = host, port
        self._handle = handle
        self._reject = reject
        self.max_clients = max_clients
        self.max_event_bytes = max_event_bytes
        self.idle_timeout_s = idle_timeout_s
        #: Connection outcomes: idle_closed (accepts, refusals and evictions: ``stats``).
        self.counts: Counter[str] = Counter()
        self._listener = TcpListener(
            host, port, name=f"cot source {name}", max_connections=max_clients
        )
        self.stats = self._listener.stats
        self._log_limit = RateLimit(interval_s=10.0)
        self.log = log.bind(source=name)

    @property
    def active(self) -> int:
        """Connections held now."""
        return self.stats.active

    @property
    def local_port(self) -> int:
        """The bound port (useful when the config asked for port 0)."""
        return self._listener.local_port

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Listen, report started, and serve until cancelled. Bind errors raise ``OSError``."""
        self._listener.bind()
        task_status.started()
        await self._listener.run(self._read)

    async def _read(self, connection: Connection) -> None:
        splitter = EventSplitter(self.max_event_bytes)
        while True:
            try:
                with anyio.fail_after(self.idle_timeout_s):
                    chunk = await connection.receive(65_536)
            except TimeoutError:
                self.counts["idle_closed"] += 1
                if self._log_limit.allow("idle_closed"):
                    self.log.warning(
                        "cot_connection_dropped",
                        outcome="idle_closed",
                        count=self.counts["idle_closed"],
                        idle_timeout_s=self.idle_timeout_s,
                    )
                return
            except (anyio.EndOfStream, anyio.BrokenResourceError):
                return
            fragments = splitter.fragments
            events = splitter.feed(chunk)
            for event in events:
                self._handle(event)
            if events:
                # A client that sends whole events keeps its place over idle strangers.
                connection.trusted = True
            for _ in range(splitter.fragments - fragments):
                self._reject("fragment")
            if splitter.is_overflowing:
                # No </event> within the limit: a stream we cannot follow; hang up.
                self._reject("oversize")
                return
