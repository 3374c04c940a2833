"""The simulated airframe's end of its UDP link: one connected socket, both directions.

Outgoing frames are sealed in the tunnel when the airframe has a ``Sealer``; what the gateway
sends back (its uplink) is opened with the sealer's reply opener, so a tunnel airframe reads
its uplink as a plain one does. Nothing the network does raises: an ICMP port unreachable
(nothing listens, the gateway is down or restarting) comes back as ``ConnectionRefusedError``
on the next send or receive of a connected socket, a lost route as ``ENETUNREACH`` and the
like; each is counted. An uplink datagram that is too big or does not open is counted and
skipped.
"""

from __future__ import annotations

import errno
import socket
from dataclasses import dataclass
from typing import TYPE_CHECKING, Self

import anyio

from gateway.errors import FrameError

if TYPE_CHECKING:
    from types import TracebackType

    from gateway.fleet.security.tunnel import Sealer

__all__ = ["MAX_UPLINK_BYTES", "AirframeLink", "LinkCounts"]

#: The largest uplink datagram read; bigger ones are rejected (a MAVLink 2 frame is 280 bytes).
MAX_UPLINK_BYTES = 8192
# recv() with a buffer one byte larger tells an oversize datagram from one that fits exactly.
_RECV_BYTES = MAX_UPLINK_BYTES + 1
#: What the network reports when nobody listens or there is no way there: a link outage.
_UNREACHABLE = frozenset(
    {errno.ECONNREFUSED, errno.EHOSTUNREACH, errno.ENETUNREACH, errno.EHOSTDOWN, errno.ENETDOWN}
)


@dataclass(slots=True)
class LinkCounts:
    """What one airframe's link saw."""

    datagrams_sent: int = 0
    """Datagrams the kernel took."""
    refused: int = 0
    """ICMP unreachable reports (nobody listened, no route): each cost one send or receive."""
    uplink_datagrams: int = 0
    """Uplink datagrams that opened (or were plain) and were handed on."""
    uplink_rejected: int = 0
    """Uplink datagrams too big, or sealed ones that did not open (forged, stale, replayed)."""


class AirframeLink:
    """A connected UDP socket to the gateway, sealing and opening when given a ``Sealer``.

    ``send`` and ``receive`` may run in different tasks; sends are serialised. Use as an
    async context manager (``connect`` creates it), or call ``close``.
    """

    def __init__(
        self, sock: socket.socket, *, sealer: Sealer | None = None, counts: LinkCounts | None = None
    ) -> None:
        sock.setblocking(False)
        self._sock = sock
        self._sealer = sealer
        self._opener = sealer.reply_opener() if sealer is not None else None
        self._sending = anyio.Lock()
        self.counts = counts if counts is not None else LinkCounts()

    @classmethod
    async def connect(
        cls, host: str, port: int, *, sealer: Sealer | None = None, counts: LinkCounts | None = None
    ) -> AirframeLink:
        """A link to ``host:port``; ``OSError`` if the name does not resolve or the socket fails."""
        family, kind, proto, _, address = (
            await anyio.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        )[0]
        sock = socket.socket(family, kind, proto)
        try:
            sock.connect(address)
        except OSError:
            sock.close()
            raise
        return cls(sock, sealer=sealer, counts=counts)

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the socket."""
        self._sock.close()

    async def send(self, frame: bytes) -> bool:
        """Send ``frame`` (sealed if the link seals) as one datagram; False if it was refused.

        A refusal reports an earlier datagram that found no listener (or no route), and the
        kernel drops this one with it; it is tried once more, since the listener may be back.
        Other ``OSError``s are raised.
        """
        data = self._sealer.seal(frame) if self._sealer is not None else frame
        async with self._sending:
            for _ in range(2):
                while True:
                    try:
                        self._sock.send(data)
                    except BlockingIOError:
                        await anyio.wait_writable(self._sock)
                        continue
                    except OSError as exc:
                        if exc.errno not in _UNREACHABLE:
                            raise
                        self.counts.refused += 1
                        break
                    self.counts.datagrams_sent += 1
                    return True
        return False

    async def receive(self) -> bytes:
        """The next uplink payload (opened, if the link seals); waits until one arrives."""
        while True:
            await anyio.wait_readable(self._sock)
            try:
                datagram = self._sock.recv(_RECV_BYTES)
            except BlockingIOError:
                continue
            except OSError as exc:
                if exc.errno not in _UNREACHABLE:
                    raise
                self.counts.refused += 1
                continue
            if len(datagram) > MAX_UPLINK_BYTES:
                self.counts.uplink_rejected += 1
                continue
            if self._opener is not None:
                try:
                    datagram = self._opener.open_frame(datagram).payload
                except FrameError:
                    self.counts.uplink_rejected += 1
                    continue
            self.counts.uplink_datagrams += 1
            return datagram
