"""The Sink contract: what an output system implements to receive events.

A sink is a small class found through the entry-point group ``fischer_gateway.sinks``. It is
constructed with its name and its own validated pydantic config, and it only encodes and
sends: the ``SinkRunner`` gives every sink the same queueing, retry, backoff, dead-lettering
and metrics, so a sink holds none of its own.

Lifetime, in the runner's one task: ``open()`` under the send deadline; then, if the sink
has one, its ``run(task_status=...)`` lifetime is started in the *runner's* task group
(``await tg.start(sink.run)``) for the background work a sink needs (a periodic announcement,
reading what a server sends); ``send(batch)`` calls, one at a time; then the lifetime is
cancelled and ``aclose()`` is called. A sink never holds a task group or a cancel scope across
``open``/``aclose``: each call returns with everything it entered exited, so the runner's
deadlines nest. If ``run`` raises, the runner closes the sink and opens it again with backoff.

``send`` raises ``TransientSinkError`` for a failure worth retrying (the peer is down, a
timeout) and ``PermanentSinkError`` for events that will never be accepted (they are
dead-lettered). A ``PermanentSinkError`` with ``event_ids`` rejects only those events: the
sink has delivered every other event of the batch before raising. Any other exception is a bug
in the sink: the runner counts it, logs it (rate-limited, with its traceback), retries the
batch a bounded number of times (``sinkrunner.ERROR_ATTEMPTS``), then sends the batch's events
one by one and dead-letters only those that still fail, so one poisoned event cannot block the
queue behind it.

A sink that can deliver without awaiting (datagrams to a non-blocking socket) may also offer
``send_now(batch) -> int`` (``SendsNow``): its runner then sends what is ready in the loop
pass's one delivery pass (``gateway.c2.deliverypass``) instead of waking its task, and falls
back to ``send`` for whatever ``send_now`` did not deliver.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

import anyio
import anyio.abc
from pydantic import BaseModel, ConfigDict

if TYPE_CHECKING:
    from gateway.events import Event, EventKind

__all__ = [
    "LifetimeSink",
    "ReleasesOwnAirframes",
    "SendsNow",
    "Sink",
    "SinkClass",
    "SinkConfig",
]


class SinkConfig(BaseModel):
    """Base of every sink's options model: frozen, unknown keys rejected."""

    model_config = ConfigDict(frozen=True, extra="forbid")


@runtime_checkable
class Sink(Protocol):
    """An output system that takes batches of events.

    ``open`` and ``aclose`` are called once per connection cycle by the runner; ``send`` is
    only called between them, never concurrently with itself, under the send deadline.
    """

    name: str

    @property
    def kinds(self) -> frozenset[EventKind]:
        """The event kinds this sink accepts; routes sending it others are a config error."""
        ...

    async def open(self) -> None:
        """Acquire connections or files. Raise ``TransientSinkError`` to be retried."""
        ...

    async def send(self, batch: Sequence[Event]) -> None:
        """Deliver every event of ``batch`` or raise; a partial success must raise too.

        ``PermanentSinkError(event_ids=...)`` names the events refused for good, after the
        others were delivered.
        """
        ...

    async def aclose(self) -> None:
        """Release what ``open`` acquired. Must be safe to call after a failed ``open``."""
        ...


@runtime_checkable
class LifetimeSink(Sink, Protocol):
    """A sink with background work, which it does in tasks its runner owns.

    ``run`` is started with ``await task_group.start(sink.run)`` after a successful ``open``
    and cancelled before ``aclose``; it calls ``task_status.started()`` once ready and then
    works until cancelled. It may run concurrently with ``send``.
    """

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Do the sink's background work until cancelled; raise to have the sink reopened."""
        ...


@runtime_checkable
class SendsNow(Protocol):
    """A sink that can deliver a batch synchronously, without blocking, when nothing is in
    the way (room in a socket's buffer). Optional; ``send`` still does all the rest."""

    def send_now(self, batch: Sequence[Event]) -> int:
        """Deliver the leading events of ``batch`` that go out without waiting; how many.

        ``batch[:n]`` is delivered (to every destination), ``batch[n:]`` is not: the runner
        sends it with ``send`` (a destination that took part of event ``n`` gets it again,
        as after any retry). Return before an event that needs a wait, a retry or a refusal
        (``send`` decides those); never block, never await. An exception counts as 0
        delivered. Called only between ``open`` and ``aclose`` while no ``send`` is in flight.
        """
        ...


@runtime_checkable
class ReleasesOwnAirframes(Protocol):
    """A sink that sends our own airframes under identities a peer may echo back to a source.

    The gateway refuses a source's ``BlueForce`` under one of these uids: it is our own
    airframe coming back (or forged), not a friendly unit.
    """

    def own_uids(self, airframes: Sequence[str]) -> frozenset[str]:
        """The ``BlueForce`` uids a source would give this sink's tracks of ``airframes``."""
        ...


class SinkClass(Protocol):
    """What an entry point of group ``fischer_gateway.sinks`` must load: a sink factory."""

    config_model: ClassVar[type[SinkConfig]]

    def __call__(self, name: str, config: Any) -> Sink:
        """Build the sink ``name`` from its validated options."""
        ...
