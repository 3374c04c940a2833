"""A UDP relay between a simulated airframe and the gateway that can cut the link.

``UdpCut(target_port)`` listens on 127.0.0.1 (``port``) and relays every datagram to the
gateway's port and every answer back to the last sender, from a thread. While ``cut`` is
True both directions are dropped and counted: the radio link is gone, in both directions, as
far as either side can tell.
"""

from __future__ import annotations

import selectors
import socket
import threading
from types import TracebackType

__all__ = ["UdpCut"]


class UdpCut:
    """A loopback UDP relay with a switch."""

    def __init__(self, target_port: int) -> None:
        self.target = ("127.0.0.1", target_port)
        self.cut = False
        self.relayed = 0
        self.dropped = 0
        self._front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._front.bind(("127.0.0.1", 0))
        self.port = int(self._front.getsockname()[1])
        self._back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._back.bind(("127.0.0.1", 0))
        self._client: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> UdpCut:
        self._thread.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._front.close()
        self._back.close()

    def _run(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self._front, selectors.EVENT_READ)
            selector.register(self._back, selectors.EVENT_READ)
            while not self._stop.is_set():
                for key, _ in selector.select(timeout=0.1):
                    sock = key.fileobj
                    assert isinstance(sock, socket.socket)
                    try:
                        data, sender = sock.recvfrom(65535)
                    except OSError:
                        continue  # ICMP port unreachable from a gateway that is down
                    if self.cut:
                        self.dropped += 1
                        continue
                    try:
                        if sock is self._front:
                            self._client = sender
                            self._back.sendto(data, self.target)
                        elif self._client is not None:
                            self._front.sendto(data, self._client)
                    except OSError:
                        continue
                    self.relayed += 1
