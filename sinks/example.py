"""An example sink for sink authors: each event as one JSON datagram over UDP.

Not registered as an entry point: it is here to be read, copied and checked
(docs/writing-a-sink.md shows it whole; ``gateway.contract.check_sink`` runs against it in
the tests). It uses only the public surface: ``gateway`` and ``gateway.contract``.
"""

from __future__ import annotations

from collections.abc import Sequence

import anyio
import anyio.abc
from pydantic import Field

from gateway import (
    Event,
    EventKind,
    PermanentSinkError,
    SinkConfig,
    TransientSinkError,
)

__all__ = ["ExampleSink", "ExampleSinkConfig"]


class ExampleSinkConfig(SinkConfig):
    """Options of the example sink (``sinks[].options`` in the config)."""

    host: str = "127.0.0.1"
    port: int = Field(ge=1, le=65535)
    kinds: frozenset[EventKind] = frozenset({EventKind.TELEMETRY, EventKind.DETECTION})
    max_datagram_bytes: int = Field(default=1400, ge=64, le=65507)


class ExampleSink:
    """Sends each event as one UDP datagram holding its JSON (``event.model_dump_json()``)."""

    config_model = ExampleSinkConfig

    def __init__(self, name: str, config: ExampleSinkConfig) -> None:
        self.name = name  # the config's sinks[].name: in logs, metrics and errors
        self.config = config
        self._socket: anyio.abc.ConnectedUDPSocket | None = None

    @property
    def kinds(self) -> frozenset[EventKind]:
        """The kinds this sink takes; a route sending it another kind is a config error."""
        return self.config.kinds

    async def open(self) -> None:
        """Create the socket; ``TransientSinkError`` (retried) if that fails."""
        try:
            self._socket = await anyio.create_connected_udp_socket(
                self.config.host, self.config.port
            )
        except OSError as exc:
            raise TransientSinkError(
                f"sink {self.name}: cannot reach {self.config.host}:{self.config.port}: "
                f"{exc.strerror or exc}",
                sink=self.name,
            ) from exc

    async def send(self, batch: Sequence[Event]) -> None:
        """Send every event of ``batch``, in order, or raise.

        ``PermanentSinkError`` for an event too large for one datagram (it never will
        fit: dead-lettered); ``TransientSinkError`` when the network refuses (retried).
        """
        if self._socket is None:
            raise TransientSinkError(f"sink {self.name}: not open", sink=self.name)
        for event in batch:
            data = event.model_dump_json().encode()
            if len(data) > self.config.max_datagram_bytes:
                raise PermanentSinkError(
                    f"sink {self.name}: event {event.event_id} is {len(data)} bytes, "
                    f"more than max_datagram_bytes {self.config.max_datagram_bytes}",
                    sink=self.name,
                )
            try:
                await self._socket.send(data)
            except OSError as exc:
                raise TransientSinkError(
                    f"sink {self.name}: send failed: {exc.strerror or exc}", sink=self.name
                ) from exc

    async def aclose(self) -> None:
        """Close the socket; safe when ``open`` never ran or failed."""
        if self._socket is not None:
            sock, self._socket = self._socket, None
            await sock.aclose()
