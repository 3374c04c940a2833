"""Hypercorn serving the map's application inside the daemon's event loop.

``hypercorn.asyncio.serve`` with a ``shutdown_trigger`` installs no signal handlers, so
SIGTERM (drain) and SIGHUP (reload) stay the daemon's. The listening socket is the sink's
own (bound in ``open``, so a port in use is the sink's error and port 0 is known at once);
hypercorn gets a duplicate of it. Hypercorn's own log lines go to structlog, rate-limited.
"""

from __future__ import annotations

import asyncio
import os
import socket
import ssl
from collections.abc import Awaitable, Callable
from typing import Any

import structlog
from hypercorn.asyncio import serve
from hypercorn.config import Config as HyperConfig
from hypercorn.logging import Logger as HyperLogger

from gateway.ops.logsetup import RateLimit
from sinks.map.config import MapTls

__all__ = ["IDLE_S", "listen", "serve_app"]

log = structlog.get_logger(__name__)

#: A connection that has not sent a whole request within this many seconds is closed.
IDLE_S = 5.0
_BACKLOG = 64


def listen(host: str, port: int, stall_s: float | None = None) -> socket.socket:
    """A TCP socket bound to ``host``:``port`` and listening; ``OSError`` if it cannot.

    With ``stall_s``, a connection whose client has taken nothing sent to it for that many
    seconds (its receive window stays shut, or nothing is acknowledged) is aborted by the
    kernel: ``TCP_USER_TIMEOUT``, which the accepted connections inherit (Linux). A stream
    whose client stopped reading is otherwise stuck in its write for good, holding one of
    ``max_connections`` places.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    infos = socket.getaddrinfo(host, port, family=0, type=socket.SOCK_STREAM)
    family, _, _, _, address = infos[0] if infos else (family, 0, 0, "", (host, port))
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if stall_s is not None and hasattr(socket, "TCP_USER_TIMEOUT"):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, round(stall_s * 1000))
        sock.bind(address)
        sock.listen(_BACKLOG)
        sock.setblocking(False)
    except OSError:
        sock.close()
        raise
    return sock


class _Log(HyperLogger):
    """Hypercorn's logger speaking structlog: errors rate-limited, no access lines."""

    _limit = RateLimit(30.0)

    def __init__(self, config: HyperConfig) -> None:  # no stdlib loggers
        self.access_logger = None
        self.error_logger = None
        self.access_log_format = config.access_log_format

    async def access(self, request: Any, response: Any, request_time: float) -> None:
        return None

    async def info(self, message: str, *args: Any, **kwargs: Any) -> None:
        return None  # "Running on ...": the sink logs its own map_listening

    async def debug(self, message: str, *args: Any, **kwargs: Any) -> None:
        return None

    async def warning(self, message: str, *args: Any, **kwargs: Any) -> None:
        self._emit("warning", message, args)

    async def error(self, message: str, *args: Any, **kwargs: Any) -> None:
        self._emit("error", message, args)

    async def critical(self, message: str, *args: Any, **kwargs: Any) -> None:
        self._emit("error", message, args)

    async def exception(self, message: str, *args: Any, **kwargs: Any) -> None:
        if self._limit.allow(("exception", message)):
            log.error("map_server_error", detail=_format(message, args), exc_info=True)

    async def log(self, level: int, message: str, *args: Any, **kwargs: Any) -> None:
        self._emit("warning", message, args)

    def _emit(self, level: str, message: str, args: tuple[Any, ...]) -> None:
        if self._limit.allow((level, message)):
            getattr(log, level)("map_server_" + level, detail=_format(message, args))


def _format(message: str, args: tuple[Any, ...]) -> str:
    try:
        return (message % args if args else message)[:500]
    except (TypeError, ValueError):
        return message[:500]


def _config(sock: socket.socket, tls: MapTls | None) -> HyperConfig:
    config = HyperConfig()
    config.bind = [f"fd://{os.dup(sock.fileno())}"]
    config.logger_class = _Log
    config.accesslog = None
    config.errorlog = None
    config.keep_alive_timeout = IDLE_S
    config.graceful_timeout = 2.0
    config.h11_max_incomplete_size = 16 * 1024
    config.include_server_header = False
    config.alpn_protocols = ["http/1.1"]
    config.ssl_handshake_timeout = IDLE_S
    if tls is not None:
        config.certfile = str(tls.cert_file)
        config.keyfile = str(tls.key_file)
        if tls.client_ca_file is not None:
            config.ca_certs = str(tls.client_ca_file)
            config.verify_mode = ssl.CERT_REQUIRED
    return config


async def serve_app(
    app: Callable[..., Awaitable[None]],
    sock: socket.socket,
    tls: MapTls | None,
    shutdown: asyncio.Event,
) -> None:
    """Serve ``app`` on ``sock`` until ``shutdown`` is set."""
    await serve(app, _config(sock, tls), shutdown_trigger=shutdown.wait, mode="asgi")
