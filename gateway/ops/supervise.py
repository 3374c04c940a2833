"""Keep one component running: start it under a deadline, restart it with backoff when it fails.

Used for the parts of the daemon that third parties write (processors, sources): a bug there
degrades that part, never the daemon. ``supervise`` calls ``task_status.started()`` once the
component has started the first time, or when its first start failed (the daemon starts
without it, degraded); a component that does not report started within ``start_timeout_s``
counts as failed. The backoff grows while it keeps failing and is reset only after it has run
for ``stable_s``; its state and the reason of the last failure are on the ``Supervised`` record.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any

import anyio
import anyio.abc
import structlog

from gateway.ops.logsetup import RateLimit

__all__ = ["Supervised", "supervise"]

log = structlog.get_logger(__name__)

Start = Callable[..., Coroutine[Any, Any, None]]
"""The component's ``run(*, task_status)``."""


@dataclass(slots=True)
class Supervised:
    """What the supervisor knows of one component, for /status."""

    name: str
    state: str = "starting"
    reason: str = ""
    restarts: int = 0


def _reason(exc: BaseException) -> str:
    while isinstance(exc, BaseExceptionGroup) and len(exc.exceptions) == 1:
        exc = exc.exceptions[0]
    return f"{type(exc).__name__}: {exc}"


async def supervise(
    run: Start,
    record: Supervised,
    *,
    what: str,
    start_timeout_s: float = 10.0,
    stable_s: float = 10.0,
    initial_backoff_s: float = 0.5,
    max_backoff_s: float = 30.0,
    task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
) -> None:
    """Run ``run`` until cancelled; see the module docstring."""
    delay = initial_backoff_s
    reported = False
    limit = RateLimit(interval_s=10.0)
    bound = log.bind(**{what: record.name})
    while True:
        started_at: float | None = None
        try:
            async with anyio.create_task_group() as tg:
                with anyio.fail_after(start_timeout_s):
                    await tg.start(run)
                started_at = anyio.current_time()
                record.state, record.reason = "running", ""
                if not reported:
                    task_status.started()
                    reported = True
        except Exception as exc:  # noqa: BLE001 - isolation boundary: a plugin's fault
            record.restarts += 1
            record.state = "restarting"
            record.reason = (
                f"did not report started within {start_timeout_s} s"
                if started_at is None and isinstance(exc, TimeoutError)
                else _reason(exc)
            )
            if limit.allow("failed"):
                bound.error(f"{what}_failed", reason=record.reason, restarts=record.restarts)
        else:
            record.state, record.reason = "restarting", "its run returned"
        if not reported:
            task_status.started()  # degraded, not fatal: the daemon starts without it
            reported = True
        if started_at is not None and anyio.current_time() - started_at >= stable_s:
            delay = initial_backoff_s
        await anyio.sleep(delay * random.uniform(0.5, 1.0))  # noqa: S311 - jitter
        delay = min(delay * 2, max_backoff_s)
