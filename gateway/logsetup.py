"""Logging configuration (called only from the CLI) and a rate limiter for noisy events.

JSON lines on the chosen stream for journald, or the console renderer on a terminal.
Loggers are cached on first use and filter below the configured level.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Hashable
from typing import TextIO

import structlog

__all__ = ["RateLimit", "configure_logging"]

_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING}
_LEVELS["error"] = logging.ERROR


def configure_logging(level: str = "info", stream: TextIO | None = None) -> None:
    """Configure structlog: JSON unless ``stream`` is a terminal, filtered at ``level``."""
    stream = stream or sys.stdout
    renderer: structlog.typing.Processor = (
        structlog.dev.ConsoleRenderer() if stream.isatty() else structlog.processors.JSONRenderer()
    )
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            structlog.processors.dict_tracebacks,
            renderer,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(_LEVELS[level]),
        logger_factory=structlog.PrintLoggerFactory(stream),
        cache_logger_on_first_use=True,
    )


class RateLimit:
    """Allows one log record per key per interval; the caller still counts every event."""

    __slots__ = ("_interval_s", "_last")

    def __init__(self, interval_s: float) -> None:
        self._interval_s = interval_s
        self._last: dict[Hashable, float] = {}

    def allow(self, key: Hashable) -> bool:
        """True if a record for ``key`` may be written now."""
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self._interval_s:
            return False
        self._last[key] = now
        return True
