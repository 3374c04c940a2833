"""A minimal third-party sink, as a package outside this repo would write it.

mypy checks this file in CI (``[tool.mypy] files``): if the public Sink contract changes in a
way that would break such a sink, the type check fails here first.
"""

from __future__ import annotations

from collections.abc import Sequence

import anyio
import anyio.abc

from gateway import (
    Event,
    EventKind,
    LifetimeSink,
    PermanentSinkError,
    Sink,
    SinkConfig,
    TransientSinkError,
)


class CountingSinkConfig(SinkConfig):
    """Options: which kinds, and when to pretend the peer is down."""

    kinds: frozenset[EventKind] = frozenset({EventKind.TELEMETRY})
    fail_after: int | None = None


class CountingSink:
    """Counts what it is sent."""

    config_model = CountingSinkConfig

    def __init__(self, name: str, config: CountingSinkConfig) -> None:
        self.name = name
        self.config = config
        self.count = 0

    @property
    def kinds(self) -> frozenset[EventKind]:
        """What this sink accepts."""
        return self.config.kinds

    async def open(self) -> None:
        """Nothing to open."""

    async def send(self, batch: Sequence[Event]) -> None:
        """Count, or fail transiently past the configured limit; refuse empty ids by id."""
        limit = self.config.fail_after
        if limit is not None and self.count >= limit:
            raise TransientSinkError("peer down", sink=self.name)
        refused = [e.event_id for e in batch if not e.event_id]
        self.count += len(batch) - len(refused)
        if refused:
            raise PermanentSinkError("no event id", sink=self.name, event_ids=refused)

    async def aclose(self) -> None:
        """Nothing to close."""


def as_sink(sink: CountingSink) -> Sink:
    """Structural typing: a CountingSink is a Sink without inheriting from anything."""
    return sink


class HeartbeatSink(CountingSink):
    """A sink with background work: a lifetime its runner starts and cancels."""

    def __init__(self, name: str, config: CountingSinkConfig) -> None:
        super().__init__(name, config)
        self.beats = 0

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Beat once a second until cancelled."""
        task_status.started()
        while True:
            self.beats += 1
            await anyio.sleep(1.0)


def as_lifetime_sink(sink: HeartbeatSink) -> LifetimeSink:
    """Structural typing again: ``run`` makes it a LifetimeSink, and it is still a Sink."""
    plain: Sink = sink
    assert plain is sink
    return sink
