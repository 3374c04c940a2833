"""Transports to airframes: UDP (listen, connect), TCP (client, server) and serial.

Each link reads bytes and hands them, with a peer key, to ``on_data``; a stream peer that
goes away is reported to ``on_close`` so its parser is dropped. Links bound by several
airframes (one UDP port for a fleet) are opened once and demultiplexed by sysid later.

Every link is a component with ``run(task_status=...)``: it reports started once its socket
is bound (or, for clients, once the first connection attempt has been made, so a dead
peer does not hold up start-up) and runs until cancelled. Stream clients reconnect with
jittered exponential backoff, one attempt at a time.
"""

from __future__ import annotations

import asyncio
import os
import random
import socket
from collections.abc import Callable

import anyio
import anyio.abc
import structlog

from gateway.config import Endpoint, LinkConfig
from gateway.errors import LinkClosed, LinkUnavailable

__all__ = ["DataHandler", "Link", "make_link"]

log = structlog.get_logger(__name__)

DataHandler = Callable[[str, object, bytes], None]
"""``on_data(link_label, peer, data)``: synchronous, must not raise."""
CloseHandler = Callable[[str, object], None]

_READ_CHUNK = 4096


class Link:
    """Base of the transports: identity, counters shown on /status, outbound sends."""

    def __init__(self, config: LinkConfig, on_data: DataHandler, on_close: CloseHandler) -> None:
        self.config = config
        self.endpoint: Endpoint = config.uri
        self.label = config.label
        self.on_data = on_data
        self.on_close = on_close
        self.is_bound = False
        self.state = "starting"
        self.reason = ""
        self.connects = 0
        self.log = log.bind(link=self.label)

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Open the transport, report started, and read until cancelled."""
        raise NotImplementedError

    async def send(self, data: bytes) -> None:
        """Send ``data`` to the peer(s); raise ``LinkError`` if there is none."""
        raise NotImplementedError

    def status(self) -> dict[str, object]:
        """The link's state for /status."""
        return {
            "link": self.label,
            "uri": str(self.endpoint),
            "bound": self.is_bound,
            "state": self.state,
            "reason": self.reason,
            "connects": self.connects,
        }


class _DatagramProtocol(asyncio.DatagramProtocol):
    # asyncio's protocol callback is used instead of anyio's UDP socket iterator because it
    # delivers each datagram with one call and no coroutine switch: it is the ingest hot path.
    def __init__(self, link: UdpLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.link.peers.add(addr)
        self.link.on_data(self.link.label, addr, data)

    def error_received(self, exc: Exception) -> None:
        self.link.log.warning("udp_error_received", error=str(exc))


class UdpLink(Link):
    """UDP: ``listen`` binds HOST:PORT and answers whoever sent; ``connect`` sends to it."""

    def __init__(self, config: LinkConfig, on_data: DataHandler, on_close: CloseHandler) -> None:
        super().__init__(config, on_data, on_close)
        self.peers: set[tuple[str, int]] = set()
        self._transport: asyncio.DatagramTransport | None = None

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        loop = asyncio.get_running_loop()
        ep = self.endpoint
        try:
            if ep.mode == "listen":
                transport, _ = await loop.create_datagram_endpoint(
                    lambda: _DatagramProtocol(self), local_addr=(ep.host, ep.port)
                )
            else:
                transport, _ = await loop.create_datagram_endpoint(
                    lambda: _DatagramProtocol(self), remote_addr=(ep.host, ep.port)
                )
        except OSError as exc:
            raise LinkUnavailable(self.label, f"cannot open {ep}: {exc.strerror or exc}") from exc
        self._transport = transport
        sock = transport.get_extra_info("socket")
        # A burst of frames after a radio fade must not overflow the kernel's default buffer.
        if sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 * 1024 * 1024)
            except OSError:
                self.log.info("udp_rcvbuf_not_raised")
        self.is_bound, self.state = True, "bound"
        self.log.info("link_bound", uri=str(ep), local=str(transport.get_extra_info("sockname")))
        task_status.started()
        try:
            await anyio.sleep_forever()
        finally:
            self.is_bound, self.state = False, "closed"
            transport.close()

    @property
    def local_port(self) -> int:
        """The bound port (useful when the config asked for port 0)."""
        if self._transport is None:
            return 0
        return int(self._transport.get_extra_info("sockname")[1])

    def send_nowait(self, data: bytes) -> bool:
        """Send without waiting (UDP never blocks); False if there is nobody to send to."""
        transport = self._transport
        if transport is None:
            return False
        if self.endpoint.mode == "connect":
            transport.sendto(data)
            return True
        for peer in self.peers:
            transport.sendto(data, peer)
        return bool(self.peers)

    async def send(self, data: bytes) -> None:
        transport = self._transport
        if transport is None:
            raise LinkUnavailable(self.label, "not open")
        if self.endpoint.mode == "connect":
            transport.sendto(data)
        elif not self.peers:
            raise LinkUnavailable(self.label, "no peer has been heard yet")
        else:
            for peer in self.peers:
                transport.sendto(data, peer)


class _StreamLink(Link):
    """Shared read loop of TCP and serial streams."""

    async def _pump(self, stream: anyio.abc.ByteReceiveStream, peer: object) -> None:
        try:
            while True:
                try:
                    data = await stream.receive(_READ_CHUNK)
                except (anyio.EndOfStream, anyio.BrokenResourceError) as exc:
                    raise LinkClosed(self.label, f"peer {peer} closed the stream") from exc
                self.on_data(self.label, peer, data)
        finally:
            self.on_close(self.label, peer)


class TcpClientLink(_StreamLink):
    """TCP client: connects, reads, and on any failure reconnects with jittered backoff."""

    def __init__(self, config: LinkConfig, on_data: DataHandler, on_close: CloseHandler) -> None:
        super().__init__(config, on_data, on_close)
        self._stream: anyio.abc.SocketStream | None = None

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        ep = self.endpoint
        delay = self.config.reconnect_initial_s
        started = False
        self.is_bound = True  # a client has nothing to bind; readiness does not wait on a peer
        while True:
            try:
                with anyio.fail_after(max(delay, 5.0)):
                    stream = await anyio.connect_tcp(ep.host, ep.port)
            except (OSError, TimeoutError) as exc:
                self.state, self.reason = "reconnecting", f"connect failed: {exc}"
                self.log.warning("link_connect_failed", uri=str(ep), error=str(exc))
            else:
                self.connects += 1
                self.state, self.reason = "connected", ""
                self.log.info("link_connected", uri=str(ep))
                delay = self.config.reconnect_initial_s
                if not started:
                    task_status.started()
                    started = True
                self._stream = stream
                try:
                    async with stream:
                        await self._pump(stream, (ep.host, ep.port))
                except LinkClosed as exc:
                    self.state, self.reason = "reconnecting", str(exc)
                    self.log.warning("link_closed", uri=str(ep))
                finally:
                    self._stream = None
            if not started:
                task_status.started()
                started = True
            await anyio.sleep(delay * random.uniform(0.5, 1.0))  # noqa: S311 - jitter
            delay = min(delay * 2, self.config.reconnect_max_s)

    async def send(self, data: bytes) -> None:
        if self._stream is None:
            raise LinkUnavailable(self.label, "not connected")
        await self._stream.send(data)


class TcpServerLink(_StreamLink):
    """TCP server: each accepted connection is a peer with its own parser."""

    def __init__(self, config: LinkConfig, on_data: DataHandler, on_close: CloseHandler) -> None:
        super().__init__(config, on_data, on_close)
        self._streams: dict[object, anyio.abc.SocketStream] = {}
        self.local_port = 0

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        ep = self.endpoint
        try:
            listener = await anyio.create_tcp_listener(local_host=ep.host, local_port=ep.port)
        except OSError as exc:
            raise LinkUnavailable(
                self.label, f"cannot listen on {ep}: {exc.strerror or exc}"
            ) from exc
        self.local_port = int(listener.extra(anyio.abc.SocketAttribute.local_port))
        self.is_bound, self.state = True, "listening"
        self.log.info("link_bound", uri=str(ep), port=self.local_port)
        task_status.started()
        async with listener:
            await listener.serve(self._serve)

    async def _serve(self, stream: anyio.abc.SocketStream) -> None:
        peer = stream.extra(anyio.abc.SocketAttribute.remote_address)
        self.connects += 1
        self._streams[peer] = stream
        self.log.info("link_peer_connected", peer=str(peer))
        try:
            async with stream:
                await self._pump(stream, peer)
        except LinkClosed:
            self.log.info("link_peer_closed", peer=str(peer))
        finally:
            self._streams.pop(peer, None)

    async def send(self, data: bytes) -> None:
        if not self._streams:
            raise LinkUnavailable(self.label, "no peer connected")
        for stream in list(self._streams.values()):
            await stream.send(data)


class SerialLink(Link):
    """A serial device (radio modem), read without a thread through the event loop."""

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        ep = self.endpoint
        try:
            fd = self._open(ep.device, ep.baud)
        except OSError as exc:
            raise LinkUnavailable(
                self.label, f"cannot open {ep.device}: {exc.strerror or exc}"
            ) from exc
        self._fd: int | None = fd
        self.is_bound, self.state = True, "open"
        self.log.info("link_bound", uri=str(ep))
        task_status.started()
        peer = ep.device
        try:
            while True:
                await anyio.wait_readable(fd)
                try:
                    data = os.read(fd, _READ_CHUNK)
                except BlockingIOError:
                    continue
                except OSError as exc:
                    raise LinkClosed(self.label, f"read failed: {exc.strerror}") from exc
                if not data:
                    raise LinkClosed(self.label, "device closed")
                self.on_data(self.label, peer, data)
        finally:
            self.on_close(self.label, peer)
            self.is_bound, self.state, self._fd = False, "closed", None
            os.close(fd)

    @staticmethod
    def _open(device: str, baud: int) -> int:
        import termios

        fd = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            attrs = termios.tcgetattr(fd)
            speed = getattr(termios, f"B{baud}", None)
            if speed is None:
                raise OSError(f"unsupported baud rate {baud}")
            # Raw 8N1: no line discipline may touch binary MAVLink bytes.
            attrs[0] = 0
            attrs[1] = 0
            attrs[2] = termios.CS8 | termios.CREAD | termios.CLOCAL
            attrs[3] = 0
            attrs[4] = attrs[5] = speed
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        except termios.error as exc:
            if not os.isatty(fd):
                os.close(fd)
                raise OSError(f"{device} is not a terminal device") from exc
            os.close(fd)
            raise OSError(str(exc)) from exc
        except OSError:
            os.close(fd)
            raise
        return fd

    async def send(self, data: bytes) -> None:
        fd = getattr(self, "_fd", None)
        if fd is None:
            raise LinkUnavailable(self.label, "not open")
        view = memoryview(data)
        while view:
            await anyio.wait_writable(fd)
            try:
                written = os.write(fd, view)
            except BlockingIOError:
                continue
            view = view[written:]


def make_link(config: LinkConfig, on_data: DataHandler, on_close: CloseHandler) -> Link:
    """Build the transport a link's URI names."""
    ep = config.uri
    if ep.scheme == "udp":
        return UdpLink(config, on_data, on_close)
    if ep.scheme == "tcp":
        cls = TcpServerLink if ep.mode == "listen" else TcpClientLink
        return cls(config, on_data, on_close)
    return SerialLink(config, on_data, on_close)
