"""The CoT source's TCP side: a bounded listener for ATAK/WinTAK streams, and the splitter.

A stream is XML events back to back, split after each ``</event>`` (``cot.md`` §6). The
splitter resynchronises on the last ``<event`` (with its ``<?xml`` declaration) before each
end, so a stray fragment (a bare ``<detail>``, half an event after a reconnect) costs only
itself: it is counted, and the event after it still parses.

The listener bounds what peers can hold: ``max_clients`` connections at once (more are closed
at once and counted), ``idle_timeout_s`` of silence closes a connection, and each connection
buffers at most ``max_event_bytes``. An accept error (EMFILE when the process is out of file
descriptors, ENOBUFS, ECONNABORTED) is counted and logged rate-limited, and the listener waits
``ACCEPT_RETRY_S`` and goes on: it degrades this one source, never the daemon.
"""

from __future__ import annotations

import errno
import re
import socket
from collections import Counter
from collections.abc import Callable

import anyio
import anyio.abc
import structlog

from gateway.logsetup import RateLimit

__all__ = ["ACCEPT_RETRY_S", "CotStreamServer", "EventSplitter"]

log = structlog.get_logger(__name__)

#: After an accept error, wait this long before accepting again (the connection stays queued).
ACCEPT_RETRY_S = 0.25
_END = b"</event>"
_EVENT_START = re.compile(rb"<event[\s>/]")
_DECLARATION = re.compile(rb"<\?xml[^>]*\?>\s*\Z")
_RESOURCE_ERRORS = frozenset({errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM})


class EventSplitter:
    """Cuts a CoT XML stream into events, skipping (and counting) what is not one."""

    def __init__(self, max_event_bytes: int) -> None:
        self.max_event_bytes = max_event_bytes
        #: Pieces of the stream before an event that were not part of it.
        self.fragments = 0
        self._buffer = bytearray()

    @property
    def is_overflowing(self) -> bool:
        """More than ``max_event_bytes`` buffered without an ``</event>``."""
        return len(self._buffer) > self.max_event_bytes

    def feed(self, chunk: bytes) -> list[bytes]:
        """Take ``chunk``; return the events it completed, each from its ``<?xml``/``<event``."""
        self._buffer += chunk
        events: list[bytes] = []
        while (end := self._buffer.find(_END)) >= 0:
            piece = bytes(self._buffer[: end + len(_END)])
            del self._buffer[: end + len(_END)]
            starts = [m.start() for m in _EVENT_START.finditer(piece)]
            if not starts:
                self.fragments += 1  # an ``</event>`` with no event before it
                continue
            start = starts[-1]
            declaration = piece.rfind(b"<?xml", 0, start)
            if declaration >= 0 and _DECLARATION.match(piece, declaration, start):
                start = declaration
            if piece[:start].strip():
                self.fragments += 1
            events.append(piece[start:])
        return events


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
        #: Connection outcomes: accept_failed, refused, idle_closed.
        self.counts: Counter[str] = Counter()
        self.active = 0
        self.local_port = 0
        self._log_limit = RateLimit(interval_s=10.0)
        self.log = log.bind(source=name)

    def _listening_socket(self) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, self.port))
            sock.listen(min(128, self.max_clients * 2))
            sock.setblocking(False)
        except BaseException:
            sock.close()
            raise
        return sock

    def _count(self, outcome: str, **fields: object) -> None:
        self.counts[outcome] += 1
        if self._log_limit.allow(outcome):
            self.log.warning(
                "cot_connection_dropped", outcome=outcome, count=self.counts[outcome], **fields
            )

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Listen, report started, and serve until cancelled. Bind errors raise ``OSError``."""
        listener = self._listening_socket()
        with listener:
            self.local_port = int(listener.getsockname()[1])
            task_status.started()
            async with anyio.create_task_group() as tg:
                while True:
                    await anyio.wait_readable(listener)
                    try:
                        conn, _ = listener.accept()
                    except (BlockingIOError, InterruptedError):
                        continue
                    except OSError as exc:
                        code = errno.errorcode.get(exc.errno or 0, str(exc.errno))
                        self._count("accept_failed", error=code, retry_in_s=ACCEPT_RETRY_S)
                        # The connection stays queued, so the socket stays readable: wait.
                        await anyio.sleep(ACCEPT_RETRY_S)
                        continue
                    if self.active >= self.max_clients:
                        conn.close()
                        self._count("refused", max_clients=self.max_clients)
                        continue
                    self.active += 1
                    tg.start_soon(self._serve, conn)

    async def _serve(self, conn: socket.socket) -> None:
        try:
            with conn:
                conn.setblocking(False)
                await self._read(conn)
        finally:
            self.active -= 1

    async def _read(self, conn: socket.socket) -> None:
        splitter = EventSplitter(self.max_event_bytes)
        while True:
            with anyio.move_on_after(self.idle_timeout_s) as idle:
                await anyio.wait_readable(conn)
            if idle.cancelled_caught:
                self._count("idle_closed", idle_timeout_s=self.idle_timeout_s)
                return
            try:
                chunk = conn.recv(65_536)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                return  # reset by the peer: nothing to count
            if not chunk:
                return
            fragments = splitter.fragments
            for event in splitter.feed(chunk):
                self._handle(event)
            for _ in range(splitter.fragments - fragments):
                self._reject("fragment")
            if splitter.is_overflowing:
                # No </event> within the limit: a stream we cannot follow; hang up.
                self._reject("oversize")
                return
