"""One UDP peer that says when it is not there: a connected socket, refusals as ``OSError``.

``DatagramSender`` (``gateway.transports.udp``) drops the ICMP "port unreachable" of a peer
that is not listening, as UDP does: the datagram is lost and nobody is told. ``UdpPeer``
keeps the refusal, which the kernel holds as its connected socket's pending error: after
each datagram it waits ``refusal_wait_s`` for one before it calls the datagram sent. On
loopback or a LAN the ICMP answer is back well within that; from a peer further away it
surfaces at the next send.
UDP has no acknowledgement, so a datagram that is not refused may still be lost.
"""

from __future__ import annotations

import os
import socket

import anyio

__all__ = ["REFUSAL_WAIT_S", "UdpPeer"]

#: How long after a datagram a refusal (ICMP unreachable) is waited for.
REFUSAL_WAIT_S = 0.2


class UdpPeer:
    """One unicast UDP destination; ``send`` raises ``OSError`` if the peer refuses."""

    def __init__(self, host: str, port: int, *, refusal_wait_s: float = REFUSAL_WAIT_S) -> None:
        self.host = host
        self.port = port
        self.refusal_wait_s = refusal_wait_s
        self._sock: socket.socket | None = None

    async def _open(self) -> socket.socket:
        if self._sock is None:
            infos = await anyio.getaddrinfo(
                self.host, self.port, family=socket.AF_INET, type=socket.SOCK_DGRAM
            )
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.setblocking(False)
                sock.connect(infos[0][4])
            except OSError:
                sock.close()
                raise
            self._sock = sock
        return self._sock

    async def send(self, data: bytes) -> None:
        """Send ``data`` as one datagram; ``OSError`` (say ``ECONNREFUSED``) if refused.

        A refusal of this datagram, or of an earlier one reported only now, both raise: the
        caller keeps ``data`` to send again.
        """
        sock = await self._open()
        while True:
            try:
                sock.send(data)
                break
            except BlockingIOError:
                await anyio.wait_writable(sock)
        await anyio.sleep(self.refusal_wait_s)
        error = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if error:
            raise OSError(error, os.strerror(error))

    async def aclose(self) -> None:
        """Close the socket (the next ``send`` opens it again)."""
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
