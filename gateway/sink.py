"""The Sink contract: what an output system implements to receive events.

A sink is a small class found through the entry-point group ``fischer_gateway.sinks``. It is
constructed with its name and its own validated pydantic config, and it only encodes and
sends: the ``SinkRunner`` gives every sink the same queueing, retry, backoff, dead-lettering
and metrics, so a sink holds none of its own.

``send`` raises ``TransientSinkError`` for a failure worth retrying (the peer is down, a
timeout) and ``PermanentSinkError`` for events that will never be accepted (they are
dead-lettered). Any other exception is a bug in the sink; the runner treats it as transient
and logs it with its traceback.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

from pydantic import BaseModel, ConfigDict

if TYPE_CHECKING:
    from gateway.events import Event, EventKind

__all__ = ["Sink", "SinkClass", "SinkConfig"]


class SinkConfig(BaseModel):
    """Base of every sink's options model: frozen, unknown keys rejected."""

    model_config = ConfigDict(frozen=True, extra="forbid")


@runtime_checkable
class Sink(Protocol):
    """An output system that takes batches of events.

    ``open`` and ``aclose`` are called once each by the runner; ``send`` is only called
    between them, never concurrently with itself, under the configured send deadline.
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
        """Deliver every event of ``batch`` or raise; a partial success must raise too."""
        ...

    async def aclose(self) -> None:
        """Release what ``open`` acquired. Must be safe to call after a failed ``open``."""
        ...


class SinkClass(Protocol):
    """What an entry point of group ``fischer_gateway.sinks`` must load: a sink factory."""

    config_model: ClassVar[type[SinkConfig]]

    def __call__(self, name: str, config: Any) -> Sink:
        """Build the sink ``name`` from its validated options."""
        ...
