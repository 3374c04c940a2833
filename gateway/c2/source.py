"""The source contract: inputs beyond the airframes that publish events onto the bus.

A source is found through the entry-point group ``fischer_gateway.sources`` and configured
under ``sources:`` (``name``, ``type`` and its own options beside them). Built in: ``cot``
(``sources/cot.py``: friendly positions from ATAK/WinTAK/iTAK); NFFI, order intake and NATS
come the same way. A source binds in ``run`` and calls ``task_status.started()`` once bound;
it publishes events with the given ``publish`` (synchronous, never blocks; True once the event
is held durably, False if the spool refused it, so a source whose peer can send again
acknowledges only on True), must never raise
on bad input (count it instead), and reports itself on ``/status`` through ``status()``.
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime
from typing import Any, ClassVar, Protocol, runtime_checkable

import anyio
import anyio.abc
from pydantic import BaseModel

from gateway.events import Event

__all__ = ["Source", "SourceClass"]


@runtime_checkable
class Source(Protocol):
    """A running input: bound in ``run``, described by ``status``."""

    name: str

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind, report started, and receive until cancelled."""
        ...

    def status(self) -> dict[str, object]:
        """What /status shows for this source (counts by outcome, connections ...)."""
        ...


class SourceClass(Protocol):
    """What an entry point of ``fischer_gateway.sources`` must name."""

    config_model: ClassVar[type[BaseModel]]

    def __call__(
        self,
        name: str,
        config: Any,
        publish: Callable[[Event], bool],
        *,
        clock: Callable[[], datetime],
    ) -> Source: ...
