"""Fixtures of the attack tests."""

from __future__ import annotations

import socket
from collections.abc import Callable, Iterator

import pytest


@pytest.fixture
def udp_socket() -> Iterator[Callable[[], socket.socket]]:
    """Makes loopback UDP sockets, all closed when the test ends."""
    made: list[socket.socket] = []

    def make() -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        made.append(sock)
        sock.bind(("127.0.0.1", 0))
        sock.settimeout(0.3)
        return sock

    yield make
    for sock in made:
        sock.close()
