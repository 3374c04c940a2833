"""Datagrams to a unicast address or a multicast group, for any sink that speaks UDP.

``DatagramSender`` resolves the host once, opens a non-blocking socket (for a multicast group:
TTL, loopback on, and the interface to send from, by address or name) and sends each
datagram whole, waiting while the kernel's buffer is full. CoT to ATAK's SA mesh uses it
today; KLV and Ra 180's UDP radio gateway will too.

The socket is connected to its one destination: the kernel then resolves the route once,
not per datagram. A connected socket reports an ICMP error about an *earlier* datagram
(port unreachable: nobody listening yet) on the next send, which it does not send; UDP is
fire and forget, so that report is dropped, as an unconnected socket drops it, and the
datagram is sent again. An error that the second try meets too (no route) is raised.
"""

from __future__ import annotations

import errno
import socket
import struct
from ipaddress import ip_address

import anyio

__all__ = ["DatagramSender", "interface_request", "is_multicast"]

#: Errors that ICMP answers to an earlier datagram leave pending on a connected socket.
_REPORTED_LATE = frozenset(
    {errno.ECONNREFUSED, errno.EHOSTUNREACH, errno.ENETUNREACH, errno.EHOSTDOWN}
)


def is_multicast(host: str) -> bool:
    """True for an IP literal in a multicast range; False for names and unicast addresses."""
    try:
        return ip_address(host).is_multicast
    except ValueError:
        return False


def interface_request(interface: str) -> bytes:
    """``IP_MULTICAST_IF`` argument for an interface address or name (Linux ``ip_mreqn``)."""
    try:
        return socket.inet_aton(str(ip_address(interface)))
    except ValueError:
        index = socket.if_nametoindex(interface)
        return struct.pack("=4s4si", b"\0" * 4, b"\0" * 4, index)


class DatagramSender:
    """One UDP destination; ``OSError`` from ``open``/``send`` if the network refuses."""

    def __init__(self, host: str, port: int, *, ttl: int = 1, interface: str | None = None):
        self.host = host
        self.port = port
        self.ttl = ttl
        self.interface = interface
        self._sock: socket.socket | None = None
        self._opening = anyio.Lock()

    async def open(self) -> None:
        """Create the socket (resolving the host once); a no-op when open."""
        async with self._opening:
            if self._sock is None:
                await self._create()

    async def _create(self) -> None:
        infos = await anyio.getaddrinfo(
            self.host, self.port, family=socket.AF_INET, type=socket.SOCK_DGRAM
        )
        address = infos[0][4]
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            if is_multicast(str(address[0])):
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, self.ttl)
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
                if self.interface:
                    request = interface_request(self.interface)
                    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, request)
            sock.connect(address)
        except OSError:
            sock.close()
            raise
        self._sock = sock

    def send_now(self, data: bytes) -> bool:
        """Send ``data`` as one datagram if that needs no wait: True if sent, False if the
        socket is not open or its buffer is full (then ``send`` it). ``OSError`` if refused.

        No coroutine, no lock, no checkpoint: a sink's batch goes out in one call.
        """
        sock = self._sock
        if sock is None:
            return False
        try:
            sock.send(data)
        except BlockingIOError:
            return False
        except OSError as exc:
            if exc.errno not in _REPORTED_LATE:
                raise
            try:  # the report of an earlier datagram, dropped; this one was not sent
                sock.send(data)
            except BlockingIOError:
                return False
        return True

    async def send(self, data: bytes) -> None:
        """Send ``data`` as one datagram, opening the socket first if needed.

        An open socket with room in its buffer sends without yielding to the event loop
        (no lock, no checkpoint): a sink's batch goes out in one pass.
        """
        if self._sock is None:
            await self.open()
        while not self.send_now(data):
            if self._sock is None:
                raise OSError("the UDP socket is not open")
            await anyio.wait_writable(self._sock)

    async def aclose(self) -> None:
        """Close the socket (it is opened again by the next ``send``)."""
        if self._sock is not None:
            self._sock.close()
        self._sock = None
