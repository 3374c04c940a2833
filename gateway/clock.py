"""The one clock type of the gateway, and the wall clock it defaults to.

Data times are UTC-aware datetimes from a ``Clock``; components take one as a parameter so
tests control time. Deadlines use ``anyio.current_time()`` (monotonic), never this.
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import UTC, datetime

__all__ = ["Clock", "utc_now"]

Clock = Callable[[], datetime]
"""Returns the current UTC-aware time; injected so tests control it."""


def utc_now() -> datetime:
    """The wall clock, UTC-aware: the default ``Clock``."""
    return datetime.now(UTC)
