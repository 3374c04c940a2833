"""``UdpPeer``: a radio gateway that is not listening is an ``OSError``, not a silent loss."""

from __future__ import annotations

import socket

import anyio
import pytest
from daemon_support import free_udp_port

from gateway.transports.udp_peer import UdpPeer

pytestmark = pytest.mark.anyio


async def test_a_peer_not_listening_refuses_and_one_listening_receives() -> None:
    port = free_udp_port()
    peer = UdpPeer("127.0.0.1", port)
    try:
        with pytest.raises(ConnectionRefusedError):
            await peer.send(b"MAL")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as radio:
            radio.bind(("127.0.0.1", port))
            radio.setblocking(False)
            await peer.send(b"UPPD")
            with anyio.fail_after(10):
                await anyio.wait_readable(radio)
            assert radio.recv(64) == b"UPPD"
        with pytest.raises(ConnectionRefusedError):  # gone again
            await peer.send(b"UPPD")
    finally:
        await peer.aclose()
