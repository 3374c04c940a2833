"""One accept loop for every TCP listener the gateway runs: capped, and never fatal.

anyio's ``Listener.serve`` ends its task group (and with it the daemon) on the first
``accept()`` error, and accepts as many connections as the peer opens. ``serve_tcp`` instead
holds at most ``max_connections`` at once, closes any connection beyond that as soon as it is
accepted (so the kernel's backlog cannot fill the process with descriptors), and treats an
accept error (EMFILE and ENFILE when descriptors run out, ENOBUFS, ECONNABORTED) as a
degradation of this listener: it is counted, logged at most once a minute, and accepting
resumes after a short pause. Each connection's handler runs in the listener's task group;
an exception from one handler is logged and counted and ends only that connection.
"""

from __future__ import annotations

import errno
import resource
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import anyio
import anyio.abc
import structlog
from anyio.streams.stapled import MultiListener

from gateway.logsetup import RateLimit

__all__ = ["ListenerStats", "raise_open_files_limit", "serve_tcp"]

log = structlog.get_logger(__name__)

Handler = Callable[[anyio.abc.SocketStream], Awaitable[None]]

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
    """Connections closed on accept because ``max_connections`` were open."""
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
            "accept_errors": self.accept_errors,
            "handler_errors": self.handler_errors,
        }


async def serve_tcp(
    listener: anyio.abc.Listener[anyio.abc.SocketStream],
    handler: Handler,
    *,
    name: str,
    max_connections: int,
    stats: ListenerStats | None = None,
) -> ListenerStats:
    """Accept connections on ``listener`` until cancelled, each served by ``handler``.

    ``stats`` (made if not given) is updated as connections come and go. The handler owns
    its stream's deadlines; ``serve_tcp`` closes the stream when the handler returns.
    """
    stats = stats or ListenerStats(name, max_connections)
    limit = RateLimit(interval_s=_LOG_INTERVAL_S)
    children: list[Any] = (
        list(listener.listeners) if isinstance(listener, MultiListener) else [listener]
    )
    async with anyio.create_task_group() as tg:
        for child in children:
            tg.start_soon(_accept_loop, child, handler, stats, limit, tg)
    return stats


async def _accept_loop(
    listener: anyio.abc.SocketListener,
    handler: Handler,
    stats: ListenerStats,
    limit: RateLimit,
    tg: anyio.abc.TaskGroup,
) -> None:
    pause = _PAUSE_MIN_S
    while True:
        try:
            stream = await listener.accept()
        except OSError as exc:
            # Out of descriptors, buffers or a connection reset before accept: this listener
            # pauses, the daemon carries on.
            stats.accept_errors += 1
            if limit.allow(exc.errno):
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
        if stats.active >= stats.max_connections:
            stats.refused += 1
            if limit.allow("full"):
                log.warning(
                    "listener_connection_refused",
                    listener=stats.name,
                    reason="max_connections",
                    max_connections=stats.max_connections,
                    refused=stats.refused,
                )
            with anyio.CancelScope(shield=True):
                await stream.aclose()
            continue
        stats.active += 1
        stats.accepted += 1
        tg.start_soon(_serve_one, stream, handler, stats, limit)


async def _serve_one(
    stream: anyio.abc.SocketStream, handler: Handler, stats: ListenerStats, limit: RateLimit
) -> None:
    try:
        async with stream:
            await handler(stream)
    except Exception:
        stats.handler_errors += 1
        if limit.allow("handler"):
            log.exception("listener_handler_failed", listener=stats.name)
    finally:
        stats.active -= 1


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
