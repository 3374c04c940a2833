"""One TCP listener for every port the gateway serves: bounded, fair, and never fatal.

Three properties an attacker on the network must not be able to break, each learned the hard
way (docs/security.md):

- **Memory.** Connections are read straight from their non-blocking sockets (``Connection``):
  bytes stay in the kernel until a handler asks for them, so TCP flow control throttles a
  sender that is faster than we are. (anyio's stream protocol queues everything the loop
  reads; under uvloop one connection grew the daemon to 3 GB in 5 s.)
- **Descriptors.** At most ``max_connections`` at once. A new connection over the cap evicts
  the connection that has shown least (not yet ``trusted``, then least recently active); if
  every one is trusted, the new one is closed. An accept error (EMFILE and ENFILE when
  descriptors run out, ENOBUFS, ECONNABORTED) pauses this listener and is counted and logged
  at most once a minute; the daemon and the other listeners carry on.
- **Isolation.** Each connection's handler runs in the listener's task group; an exception
  from one is logged (rate-limited) and counted and ends only that connection.

A handler marks its connection ``trusted`` once the peer has proved something (a frame that
authenticated, a well-formed event), so idle or hostile connections cannot lock it out.
"""

from __future__ import annotations

import contextlib
import errno
import resource
import socket
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import anyio
import anyio.abc
import structlog

from gateway.errors import LinkUnavailable, os_reason
from gateway.ops.logsetup import RateLimit
from gateway.transports.stream import open_tcp

__all__ = [
    "Connection",
    "ListenerStats",
    "TcpListener",
    "connect",
    "raise_open_files_limit",
]

log = structlog.get_logger(__name__)

Handler = Callable[["Connection"], Awaitable[None]]

_PAUSE_MIN_S = 0.05
_PAUSE_MAX_S = 1.0
_LOG_INTERVAL_S = 60.0


@dataclass(slots=True)
class ListenerStats:
    """What a listener did, for /status and metrics."""

    name: str
    max_connections: int
    active: int = 0
    accepted: int = 0
    refused: int = 0
    """Connections closed on accept: at the cap with every held connection trusted."""
    evicted: int = 0
    """Held connections closed to make room for a new one."""
    accept_errors: int = 0
    handler_errors: int = 0

    def status(self) -> dict[str, object]:
        """The counters as a dict, for /status."""
        return {
            "listener": self.name,
            "active": self.active,
            "max_connections": self.max_connections,
            "accepted": self.accepted,
            "refused": self.refused,
            "evicted": self.evicted,
            "accept_errors": self.accept_errors,
            "handler_errors": self.handler_errors,
        }


class Connection:
    """One accepted TCP connection, read and written directly on its non-blocking socket."""

    def __init__(self, sock: socket.socket, peer: tuple[str, int]) -> None:
        self.sock = sock
        self.peer = peer
        self.trusted = False
        self.last_active = time.monotonic()
        self.scope = anyio.CancelScope()

    def __repr__(self) -> str:
        return f"Connection({self.peer[0]}:{self.peer[1]})"

    async def receive(self, max_bytes: int = 4096) -> bytes:
        """At most ``max_bytes``; raises ``anyio.EndOfStream`` when the peer has closed."""
        while True:
            await anyio.wait_readable(self.sock)
            try:
                data = self.sock.recv(max_bytes)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError as exc:
                raise anyio.BrokenResourceError(os_reason(exc)) from exc
            if not data:
                raise anyio.EndOfStream
            self.last_active = time.monotonic()
            return data

    async def send(self, data: bytes) -> None:
        """Send all of ``data``, waiting while the kernel's buffer is full."""
        view = memoryview(data)
        while view:
            await anyio.wait_writable(self.sock)
            try:
                sent = self.sock.send(view)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError as exc:
                raise anyio.BrokenResourceError(os_reason(exc)) from exc
            view = view[sent:]

    def send_eof(self) -> None:
        """Half-close: the peer reads to the end, then sees EOF."""
        with contextlib.suppress(OSError):  # already gone
            self.sock.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        """Stop the handler (if running) and close the socket."""
        self.scope.cancel()


class TcpListener:
    """Binds ``host:port`` and serves each connection with ``handler`` until cancelled."""

    def __init__(
        self, host: str, port: int, *, name: str, max_connections: int, what: str = ""
    ) -> None:
        self.host = host
        self.port = port
        self.what = what or name
        self.stats = ListenerStats(name, max_connections)
        self.local_port = 0
        self._held: set[Connection] = set()
        self._limit = RateLimit(interval_s=_LOG_INTERVAL_S)
        self._sock: socket.socket | None = None

    def _bind(self) -> socket.socket:
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, self.port))
            sock.listen(min(4096, max(128, self.stats.max_connections * 4)))
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            where = f"{self.what} {self.host}:{self.port}"
            raise LinkUnavailable(where, f"cannot listen: {os_reason(exc)}", what="") from exc
        return sock

    def bind(self) -> int:
        """Bind and listen now; return the port. Raises ``LinkUnavailable`` if it cannot."""
        if self._sock is None:
            self._sock = self._bind()
            self.local_port = int(self._sock.getsockname()[1])
        return self.local_port

    async def run(
        self,
        handler: Handler,
        *,
        task_status: anyio.abc.TaskStatus[int] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Bind (unless ``bind`` did), report the port, and accept until cancelled.

        Raises ``LinkUnavailable`` if the address cannot be bound.
        """
        self.bind()
        listener = self._sock
        assert listener is not None  # noqa: S101 - bound just above
        try:
            task_status.started(self.local_port)
            async with anyio.create_task_group() as tg:
                await self._accept_loop(listener, handler, tg)
        finally:
            self._sock = None
            listener.close()

    async def _accept_loop(
        self, listener: socket.socket, handler: Handler, tg: anyio.abc.TaskGroup
    ) -> None:
        stats = self.stats
        pause = _PAUSE_MIN_S
        while True:
            await anyio.wait_readable(listener)
            try:
                sock, address = listener.accept()
            except (BlockingIOError, InterruptedError):
                continue
            except OSError as exc:
                # Out of descriptors or buffers, or reset before accept: the connection stays
                # queued, so the socket stays readable; pause this listener, not the daemon.
                stats.accept_errors += 1
                if self._limit.allow(exc.errno):
                    log.warning(
                        "listener_accept_failed",
                        listener=stats.name,
                        error=errno.errorcode.get(exc.errno or 0, str(exc)),
                        accept_errors=stats.accept_errors,
                        active=stats.active,
                    )
                await anyio.sleep(pause)
                pause = min(pause * 2, _PAUSE_MAX_S)
                continue
            pause = _PAUSE_MIN_S
            sock.setblocking(False)
            if len(self._held) >= stats.max_connections and not self._evict():
                stats.refused += 1
                self._log_full("refused")
                sock.close()
                continue
            connection = Connection(sock, (str(address[0]), int(address[1])))
            self._held.add(connection)
            stats.active = len(self._held)
            stats.accepted += 1
            tg.start_soon(self._serve, connection, handler)

    def _evict(self) -> bool:
        """Close the held connection that has shown least; False if all are trusted."""
        untrusted = [c for c in self._held if not c.trusted]
        if not untrusted:
            return False
        victim = min(untrusted, key=lambda c: c.last_active)
        self._held.discard(victim)
        self.stats.active = len(self._held)
        self.stats.evicted += 1
        self._log_full("evicted")
        victim.close()
        return True

    def _log_full(self, outcome: str) -> None:
        if self._limit.allow(outcome):
            log.warning(
                "listener_full",
                listener=self.stats.name,
                outcome=outcome,
                max_connections=self.stats.max_connections,
                refused=self.stats.refused,
                evicted=self.stats.evicted,
            )

    async def _serve(self, connection: Connection, handler: Handler) -> None:
        try:
            with connection.scope, connection.sock:
                await handler(connection)
        except Exception:
            self.stats.handler_errors += 1
            if self._limit.allow("handler"):
                log.exception("listener_handler_failed", listener=self.stats.name)
        finally:
            self._held.discard(connection)
            self.stats.active = len(self._held)


async def connect(host: str, port: int) -> Connection:
    """Open a TCP connection read the same bounded way as accepted ones; raise ``OSError``."""
    sock = await open_tcp(host, port)
    address = sock.getpeername()
    return Connection(sock, (str(address[0]), int(address[1])))


def raise_open_files_limit(wanted: int = 65536) -> tuple[int, int]:
    """Raise the soft RLIMIT_NOFILE towards ``wanted`` (never past the hard limit).

    systemd's default soft limit is 1024; the unit sets ``LimitNOFILE`` and this makes the
    same true when the daemon is started by hand. Returns the (soft, hard) limits after.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if target > soft:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            log.warning("open_files_limit_not_raised", soft=soft, hard=hard)
    return soft, hard
