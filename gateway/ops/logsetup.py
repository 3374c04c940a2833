"""Logging configuration (called only from the CLI) and a rate limiter for noisy events.

JSON lines on the chosen stream, or the console renderer on a terminal. Loggers are cached
on first use and filter below the configured level; a logger bound before the last
``configure_logging`` (the CLI logs at ``info`` while it reads the config, and a sink checked
there binds its logger) keeps the class of its time, so every chain starts with a gate that
drops what is below the level configured last. Under journald (``$JOURNAL_STREAM``
names the stream's device and inode, as systemd documents) each line starts with a
``<N>`` syslog priority, which journald strips and stores, so ``journalctl -p warning``
filters. Tracebacks never carry local variables: they may hold payloads or key material.
"""

from __future__ import annotations

import asyncio
import logging
import os
import sys
import time
from collections.abc import Hashable, Mapping
from typing import Any, TextIO

import structlog
from structlog.tracebacks import ExceptionDictTransformer

__all__ = [
    "JournalPriority",
    "RateLimit",
    "configure_logging",
    "install_loop_exception_handler",
    "is_journal_stream",
]

_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING}
_LEVELS["error"] = logging.ERROR

#: syslog priorities (RFC 5424) of structlog's level names.
_PRIORITIES = {
    "debug": 7,
    "info": 6,
    "warning": 4,
    "warn": 4,
    "error": 3,
    "exception": 3,
    "critical": 2,
}

log = structlog.get_logger(__name__)

#: The level configured last: the gate of every processor chain drops what is below it.
_threshold = logging.INFO
_METHOD_LEVELS = {
    "debug": logging.DEBUG,
    "info": logging.INFO,
    "warning": logging.WARNING,
    "warn": logging.WARNING,
    "error": logging.ERROR,
    "exception": logging.ERROR,
    "critical": logging.CRITICAL,
    "fatal": logging.CRITICAL,
}


def _level_gate(
    logger: Any, method_name: str, event_dict: structlog.typing.EventDict
) -> structlog.typing.EventDict:
    """Drop an event below the level configured last (for loggers bound before it)."""
    if _METHOD_LEVELS.get(method_name, logging.INFO) < _threshold:
        raise structlog.DropEvent
    return event_dict


def is_journal_stream(stream: TextIO, env: Mapping[str, str] | None = None) -> bool:
    """True if ``stream`` is connected to journald: ``$JOURNAL_STREAM`` is its ``dev:inode``.

    systemd sets the variable for the unit's stdout/stderr; a process whose output was
    redirected elsewhere (a pipe to ``jq``, a file) inherits it but no longer matches.
    """
    value = (os.environ if env is None else env).get("JOURNAL_STREAM", "")
    dev, _, inode = value.partition(":")
    if not (value.isascii() and dev.isdigit() and inode.isdigit()):
        return False
    try:
        st = os.fstat(stream.fileno())
    except (OSError, ValueError, AttributeError):
        return False  # no file descriptor (a StringIO, a closed stream)
    return (st.st_dev, st.st_ino) == (int(dev), int(inode))


class JournalPriority:
    """Wraps a renderer and prefixes its line with ``<N>``, the event's syslog priority."""

    def __init__(self, renderer: structlog.typing.Processor) -> None:
        self._renderer = renderer

    def __call__(
        self, logger: Any, method_name: str, event_dict: structlog.typing.EventDict
    ) -> str | bytes:
        """Render ``event_dict``, then prefix the priority of its level (info if unknown)."""
        level = str(event_dict.get("level", method_name)).lower()
        prefix = f"<{_PRIORITIES.get(level, 6)}>"
        line = self._renderer(logger, method_name, event_dict)
        if isinstance(line, str):
            return prefix + line
        if isinstance(line, bytes | bytearray):
            return prefix.encode("ascii") + bytes(line)
        raise TypeError(f"JournalPriority wraps a renderer of str or bytes, got {type(line)}")


def configure_logging(
    level: str = "info", stream: TextIO | None = None, env: Mapping[str, str] | None = None
) -> None:
    """Configure structlog: JSON unless ``stream`` is a terminal, filtered at ``level``.

    ``stream`` defaults to stderr, so stdout stays free for command output and the console
    sink. ``env`` (default ``os.environ``) is where ``JOURNAL_STREAM`` is looked up.
    """
    global _threshold  # the one level every chain's gate reads
    _threshold = _LEVELS[level]
    stream = stream or sys.stderr
    processors: list[structlog.typing.Processor] = [
        _level_gate,
        structlog.contextvars.merge_contextvars,
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    if stream.isatty():
        # The console renderer formats exc_info itself (a dict traceback would make it
        # fail); plain_traceback because rich's formatter, its default, shows locals.
        processors.append(
            structlog.dev.ConsoleRenderer(exception_formatter=structlog.dev.plain_traceback)
        )
    else:
        json_renderer: structlog.typing.Processor = structlog.processors.JSONRenderer()
        if is_journal_stream(stream, env):
            json_renderer = JournalPriority(json_renderer)
        processors += [
            # structlog's own dict_tracebacks shows locals by default: never here.
            structlog.processors.ExceptionRenderer(ExceptionDictTransformer(show_locals=False)),
            json_renderer,
        ]
    structlog.configure(
        processors=processors,
        wrapper_class=structlog.make_filtering_bound_logger(_LEVELS[level]),
        logger_factory=structlog.PrintLoggerFactory(stream),
        cache_logger_on_first_use=True,
    )


def install_loop_exception_handler(loop: asyncio.AbstractEventLoop | None = None) -> None:
    """Route the event loop's unhandled errors (a failing callback, a lost task) to structlog.

    asyncio's default handler writes a multi-line traceback to stderr through ``logging``,
    which bypasses structlog: in the journal that is one line per traceback line with no
    level. Here it becomes one ``asyncio_error`` record, its traceback a field.
    """
    (loop or asyncio.get_running_loop()).set_exception_handler(_log_loop_error)


def _log_loop_error(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
    exc = context.get("exception")
    message = str(context.get("message", ""))
    suppressed = _loop_errors.allow((message, type(exc).__name__))
    if suppressed is None:
        return
    fields: dict[str, Any] = {"message": message}
    if suppressed:
        fields["suppressed"] = suppressed  # like ones not logged since the last record
    for key in ("handle", "task", "future", "callback"):
        if key in context:
            fields[key] = repr(context[key])[:200]
    if isinstance(exc, BaseException):
        fields["exc_info"] = exc
    log.error("asyncio_error", **fields)


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


class _CountingLimit:
    """``RateLimit`` that also counts what it holds back, for the next record to say."""

    __slots__ = ("_held", "_limit")

    def __init__(self, interval_s: float) -> None:
        self._limit = RateLimit(interval_s)
        self._held: dict[Hashable, int] = {}

    def allow(self, key: Hashable) -> int | None:
        """How many were held back since the last record for ``key`` (a record may be
        written now), or None (hold this one back too)."""
        if not self._limit.allow(key):
            if key in self._held or len(self._held) < _MAX_HELD_KEYS:
                self._held[key] = self._held.get(key, 0) + 1
            return None
        return self._held.pop(key, 0)


#: Keys whose held-back records are counted (the keys are the code's, few; a bound anyway).
_MAX_HELD_KEYS = 256
#: One ``asyncio_error`` record per message and exception type per this many seconds: a peer
#: can cause these (a connection a library's callback fails to close), one per connection.
LOOP_ERROR_INTERVAL_S = 30.0
_loop_errors = _CountingLimit(LOOP_ERROR_INTERVAL_S)
