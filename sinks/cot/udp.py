"""CoT over UDP: datagrams to a unicast address or a multicast group (ATAK's SA mesh).

One event per datagram, XML or TAK protocol v1 mesh protobuf; never split across datagrams
(``cot.md`` §6). Sockets are non-blocking and a datagram is sent without an await unless the
socket's buffer is full; the caller's deadline bounds each call. ``send_now`` sends one
event with no await at all, or says it cannot (the sink's runner then uses ``send``).
"""

from __future__ import annotations

from collections.abc import Sequence

import anyio

from gateway.transports.udp import DatagramSender
from sinks.cot.codec import Encoded, Encoding, tak_control
from sinks.cot.proto import mesh_frame
from sinks.cot.transport import Endpoint

__all__ = ["UdpSender"]

_MAX_DATAGRAM = 65_000


class UdpSender:
    """Datagrams to a unicast address or a multicast group: one event per datagram.

    In mesh protobuf, the TAK protocol's mesh rule (``cot.md`` §7) wants every sender to
    advertise its versions in a ``TakControl`` at least every 60 s: the control rides along
    in the next event's ``TakMessage`` once ``announce_every_s`` has passed, and ``announce``
    (called by the sink's lifetime task) sends it on its own when no event went out.
    """

    def __init__(self, endpoint: Endpoint, sink: str, *, announce_every_s: float = 30.0) -> None:
        self.endpoint = endpoint
        self.sink = sink
        self.encoding: Encoding = "mesh" if endpoint.protocol == "protobuf" else "xml"
        self.announce_every_s = announce_every_s
        self._control = tak_control()
        self._announced_at: float | None = None
        self._datagrams = DatagramSender(
            endpoint.host, endpoint.port, ttl=endpoint.ttl, interface=endpoint.interface
        )

    def announce_due_in_s(self) -> float:
        """Seconds until the next ``TakControl`` is due (0: now)."""
        if self._announced_at is None:
            return 0.0
        return max(0.0, self._announced_at + self.announce_every_s - anyio.current_time())

    async def announce(self) -> None:
        """Send a control-only ``TakMessage`` if one is due; ``OSError`` if the network refuses."""
        if self.encoding == "mesh" and self.announce_due_in_s() <= 0:
            await self._send_datagram(mesh_frame(self._control))
            self._announced_at = anyio.current_time()

    async def open(self) -> None:
        """Create the socket (resolving the host once); ``OSError`` if that fails."""
        await self._datagrams.open()

    def oversize(self, events: Sequence[Encoded]) -> list[Encoded]:
        """The events too large for one datagram in this destination's encoding."""
        return [e for e in events if len(e.get(self.encoding)) > _MAX_DATAGRAM]

    def send_now(self, event: Encoded) -> bool:
        """Send ``event``'s datagram at once; False if that needs ``send`` instead.

        False when the socket is not open or its buffer is full, when the event is too large
        for a datagram (``send`` skips it, the sink refuses it), when a ``TakControl`` is due
        (``send`` adds it), or when the network refuses (``send`` reports it).
        """
        data = event.get(self.encoding)
        if len(data) > _MAX_DATAGRAM:
            return False
        if self.encoding == "mesh" and self.announce_due_in_s() <= 0:
            return False
        try:
            return self._datagrams.send_now(data)
        except OSError:
            return False

    async def send(self, events: Sequence[Encoded]) -> None:
        """Send each event as one datagram, skipping ``oversize`` ones; ``OSError`` if refused.

        Each datagram goes straight to the non-blocking socket; only a full buffer (or a
        socket not open yet) waits, in ``DatagramSender.send``: no await per datagram.
        """
        encoding, send_now = self.encoding, self._datagrams.send_now
        for event in events:
            data = event.get(encoding)
            if len(data) > _MAX_DATAGRAM:
                continue  # the sink refuses these by id (PermanentSinkError)
            if encoding == "mesh" and self.announce_due_in_s() <= 0:
                await self._send_datagram(event.mesh_with(self._control))
                self._announced_at = anyio.current_time()
            elif not send_now(data):
                await self._send_datagram(data)

    async def _send_datagram(self, data: bytes) -> None:
        await self._datagrams.send(data)

    async def aclose(self) -> None:
        """Close the socket."""
        await self._datagrams.aclose()
