"""One delivery pass per loop pass, for the sink runners whose sinks can send without awaiting.

A published event used to wake every runner it went to: five sinks, five task wake-ups, five
deadlines and five takes, one after another, in every loop pass that carried an event. A sink
that can deliver a batch synchronously (``gateway.c2.sink.SendsNow``: the CoT sink with only
UDP destinations, ``NullSink``) lets its runner skip all of that while it is idle: the offer
puts the runner on this pass instead of waking it, and the pass, scheduled once per loop pass
(``call_soon``, after the spool's end-of-pass group commit scheduled by the first append),
calls each runner's ``deliver_now``. That takes what is ready (committing the spool's open
group first if it holds appends: nothing is sent before it is held), sends it without an
await, confirms what went out in the next group, and wakes the runner for anything the sink
could not take at once (a full socket buffer, a sink error): the runner's task then delivers
it as ever, with its deadline, retries, backoff, dead letters and one-by-one isolation.

Order per sink holds because a runner is only served here while it waits idle with nothing
in flight, from the same queues, and what it could not send goes back to their front.
"""

from __future__ import annotations

import asyncio
from typing import Protocol

import structlog

from gateway.ops.logsetup import RateLimit

__all__ = ["DeliveryPass", "PassRunner"]

log = structlog.get_logger(__name__)


class PassRunner(Protocol):
    """A runner the pass serves (``gateway.c2.sinkrunner.SinkRunner``)."""

    name: str

    def deliver_now(self) -> None:
        """Send what is ready without awaiting, or wake the runner's task for it."""
        ...

    def wake(self) -> None:
        """Wake the runner's task: it delivers what is ready itself."""
        ...


class DeliveryPass:
    """The runners to serve at the end of this loop pass, served together in one callback."""

    __slots__ = ("_error_log", "_loop", "_ready", "_scheduled", "passes")

    def __init__(self) -> None:
        self._ready: list[PassRunner] = []
        self._scheduled = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._error_log = RateLimit(interval_s=30.0)
        #: Passes run (for tests and benchmarks).
        self.passes = 0

    def ready(self, runner: PassRunner) -> bool:
        """Serve ``runner`` in this loop pass's delivery; False without a running loop."""
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return False
        if loop is not self._loop:  # first use, or a new loop: the old one's callback is gone
            self._loop, self._ready, self._scheduled = loop, [], False
        if not self._scheduled:
            loop.call_soon(self._run)
            self._scheduled = True
        self._ready.append(runner)
        return True

    def _run(self) -> None:
        self._scheduled = False
        self.passes += 1
        ready, self._ready = self._ready, []
        for runner in ready:
            try:
                runner.deliver_now()
            except Exception:  # a bug here must cost one runner a wake-up, never the others
                if self._error_log.allow(runner.name):
                    log.exception("delivery_pass_failed", sink=runner.name)
                runner.wake()
