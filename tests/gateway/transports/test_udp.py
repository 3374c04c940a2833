"""``DatagramSender``: one connected, non-blocking UDP socket per destination, fire and forget."""

from __future__ import annotations

import socket

import anyio
import pytest

from gateway.transports.udp import DatagramSender


def unused_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.mark.anyio
async def test_a_peer_not_listening_yet_is_not_an_error_and_later_datagrams_arrive() -> None:
    # Connected, the socket hears the ICMP "port unreachable" of each datagram and reports
    # it on the next send; UDP drops it as an unconnected socket would, and sends again.
    port = unused_port()
    sender = DatagramSender("127.0.0.1", port)
    assert not sender.send_now(b"not open yet")
    try:
        for n in range(3):
            await sender.send(b"nobody %d" % n)
            await anyio.sleep(0.02)  # room for the ICMP answer to come back
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver:
            receiver.bind(("127.0.0.1", port))
            receiver.settimeout(10)
            assert sender.send_now(b"first heard")
            await sender.send(b"second heard")
            assert receiver.recv(100) == b"first heard"
            assert receiver.recv(100) == b"second heard"
    finally:
        await sender.aclose()


@pytest.mark.anyio
async def test_a_closed_sender_opens_again_on_the_next_send() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver:
        receiver.bind(("127.0.0.1", 0))
        receiver.settimeout(10)
        sender = DatagramSender("127.0.0.1", receiver.getsockname()[1])
        await sender.send(b"one")
        await sender.aclose()
        assert not sender.send_now(b"closed")
        await sender.send(b"two")
        await sender.aclose()
        assert [receiver.recv(100), receiver.recv(100)] == [b"one", b"two"]
