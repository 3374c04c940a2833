"""Test doubles shipped with the gateway, for its own tests and for third-party sinks."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence

import anyio
from pydantic import Field

from gateway.c2.sink import SinkConfig
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import Event, EventKind

__all__ = [
    "MemorySink",
    "MemorySinkConfig",
    "NullSink",
    "NullSinkConfig",
    "eventually",
    "fuzz_examples",
]


class MemorySinkConfig(SinkConfig):
    """Options of the in-memory sink."""

    kinds: frozenset[EventKind] = Field(
        default=frozenset(EventKind), description="Event kinds this sink takes."
    )
    fail_transient: bool = Field(default=False, description="Every send fails, retryably.")
    fail_permanent: bool = Field(default=False, description="Every send is refused for good.")
    hang: bool = Field(default=False, description="Every send waits until cancelled.")


class MemorySink:
    """A sink that keeps every event it is sent, in order, for assertions.

    It can be told to fail (transiently or permanently) or to hang, which is how the tests
    show that one bad sink does not disturb the others.
    """

    config_model = MemorySinkConfig

    def __init__(self, name: str, config: MemorySinkConfig | None = None) -> None:
        self.name = name
        self.config = config or MemorySinkConfig()
        self.events: list[Event] = []
        self.batches = 0
        self.is_open = False
        self.fail_transient = self.config.fail_transient
        self.fail_permanent = self.config.fail_permanent
        self.hang = self.config.hang
        self._changed = anyio.Event()

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Every kind, unless the config narrows it."""
        return self.config.kinds

    async def open(self) -> None:
        """Mark the sink open."""
        self.is_open = True

    async def send(self, batch: Sequence[Event]) -> None:
        """Record ``batch``, or fail or hang as configured."""
        if self.hang:
            await anyio.sleep_forever()
        if self.fail_permanent:
            raise PermanentSinkError("memory sink told to reject", sink=self.name)
        if self.fail_transient:
            raise TransientSinkError("memory sink told to fail", sink=self.name)
        self.events.extend(batch)
        self.batches += 1
        self._changed.set()
        self._changed = anyio.Event()

    async def aclose(self) -> None:
        """Mark the sink closed."""
        self.is_open = False

    async def wait_for(self, count: int) -> list[Event]:
        """Wait until at least ``count`` events have arrived; the caller sets the deadline."""
        while len(self.events) < count:
            await self._changed.wait()
        return self.events


async def eventually(predicate: Callable[[], bool], *, interval_s: float = 0.005) -> None:
    """Wait until ``predicate()`` is true; the caller sets the deadline (``fail_after``).

    For conditions nothing signals, such as a metric reaching a value; prefer an event or
    ``MemorySink.wait_for`` where one exists.
    """
    while not predicate():  # noqa: ASYNC110 - polls a condition that has no event to wait on
        await anyio.sleep(interval_s)


class NullSinkConfig(SinkConfig):
    """Options of the null sink."""

    kinds: frozenset[EventKind] = Field(
        default=frozenset(EventKind), description="Event kinds this sink takes."
    )


class NullSink:
    """Accepts and counts events, keeping none: for benchmarks and route checks."""

    config_model = NullSinkConfig

    def __init__(self, name: str, config: NullSinkConfig | None = None) -> None:
        self.name = name
        self.config = config or NullSinkConfig()
        self.count = 0

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Every kind, unless the config narrows it."""
        return self.config.kinds

    async def open(self) -> None:
        """Nothing to open."""

    async def send(self, batch: Sequence[Event]) -> None:
        """Count the batch."""
        self.count += len(batch)

    def send_now(self, batch: Sequence[Event]) -> int:
        """Count the batch, without awaiting (``gateway.c2.sink.SendsNow``)."""
        self.count += len(batch)
        return len(batch)

    async def aclose(self) -> None:
        """Nothing to close."""


def fuzz_examples(default: int) -> int:
    """Examples per fuzz property: ``default``, or ``$FISCHER_FUZZ_EXAMPLES`` for long runs."""
    value = os.environ.get("FISCHER_FUZZ_EXAMPLES", "")
    return int(value) if value.isascii() and value.isdigit() else default
