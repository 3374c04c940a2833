"""Transports to airframes: UDP (listen, connect), TCP (client, server) and serial.

Each link reads bytes and hands them, with a peer key, to ``on_data``; a stream peer that
goes away is reported to ``on_close`` so its parser is dropped. Links bound by several
airframes (one UDP port for a fleet) are opened once and demultiplexed later, by ingest,
among the airframes configured on them. A link does not decide who its peers are: ingest
records the peer that authenticated for an airframe, and uplink goes to that peer only
(``send_to``). A TCP server link caps its connections and closes one that stays silent.

Every link is a component with ``run(task_status=...)``: it reports started once its socket
is bound (or, for clients, once the first connection attempt has been made, so a dead
peer does not hold up start-up) and runs until cancelled. Stream clients reconnect with
jittered exponential backoff, one attempt at a time.
"""

from __future__ import annotations

import asyncio
import math
import os
import random
import socket
from collections import OrderedDict
from collections.abc import Callable

import anyio
import anyio.abc
import structlog

from gateway.config import Endpoint, LinkConfig
from gateway.errors import LinkClosed, LinkUnavailable, os_reason
from gateway.ops.logsetup import RateLimit
from gateway.transports.listener import Connection, TcpListener, connect
from gateway.transports.serial import open_raw

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

    async def send_to(self, peer: object, data: bytes) -> None:
        """Send ``data`` to ``peer`` only (a key ``on_data`` reported); raise ``LinkError``.

        Links with one peer (a client, a device) ignore ``peer``.
        """
        await self.send(data)

    def trust(self, peer: object) -> None:
        """``peer`` authenticated for an airframe (a listener keeps it over strangers)."""

    def drop(self, peer: object) -> None:
        """Hang up on ``peer`` (a stream peer that only fails authentication)."""

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
    # Under uvloop (the daemon's loop) libuv reads up to 32 ready datagrams per loop pass, one
    # callback each, before the pass's telemetry flush: a burst is already taken in one pass.
    def __init__(self, link: UdpLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        link = self.link
        if link.learn_on_receive:
            link.learn_peer(addr)
        link.on_data(link.label, addr, data)

    def error_received(self, exc: Exception) -> None:
        # Typically ICMP port unreachable for a peer that went away: one per datagram sent,
        # so it is counted and logged at most once per interval.
        link = self.link
        link.send_errors += 1
        if link.error_log.allow(type(exc).__name__):
            link.log.warning("udp_error_received", error=str(exc), errors_total=link.send_errors)


_ERROR_LOG_INTERVAL_S = 60.0


class UdpLink(Link):
    """UDP: ``listen`` binds HOST:PORT; ``connect`` sends to it.

    A listening link sends only to peers it is told (``send_to``), except when built with
    ``max_learned_peers`` (the passthrough): then it remembers that many most recent senders
    (or, with ``learn_on_receive=False``, those it is told of) and ``send_nowait`` reaches them.
    """

    def __init__(
        self,
        config: LinkConfig,
        on_data: DataHandler,
        on_close: CloseHandler,
        *,
        max_learned_peers: int = 0,
        learn_on_receive: bool = True,
    ) -> None:
        super().__init__(config, on_data, on_close)
        self.max_learned_peers = max_learned_peers
        #: Learn every sender (else only those ``learn_peer`` is told of, once they proved
        #: themselves: the passthrough on a signed uplink).
        self.learn_on_receive = learn_on_receive and max_learned_peers > 0
        self.peers: OrderedDict[tuple[str, int], None] = OrderedDict()
        self.send_errors = 0
        self.error_log = RateLimit(interval_s=_ERROR_LOG_INTERVAL_S)
        self._transport: asyncio.DatagramTransport | None = None

    def learn_peer(self, addr: tuple[str, int]) -> None:
        """Remember ``addr`` as the most recent sender, forgetting the oldest beyond the cap."""
        peers = self.peers
        if addr in peers:
            peers.move_to_end(addr)
            return
        peers[addr] = None
        if len(peers) > self.max_learned_peers:
            peers.popitem(last=False)

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
            raise LinkUnavailable(self.label, f"cannot open {ep}: {os_reason(exc)}") from exc
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

    async def send_to(self, peer: object, data: bytes) -> None:
        transport = self._transport
        if transport is None:
            raise LinkUnavailable(self.label, "not open")
        if self.endpoint.mode == "connect":
            transport.sendto(data)
        elif not isinstance(peer, tuple):
            raise LinkUnavailable(self.label, "no authenticated peer to send to")
        else:
            transport.sendto(data, peer)


class _StreamLink(Link):
    """Shared read loop of TCP streams: read bounded (``Connection``), hand bytes to ingest."""

    async def _pump(self, connection: Connection, *, idle_timeout_s: float = math.inf) -> None:
        """Read until the peer closes (``LinkClosed``); an untrusted peer has one timeout."""
        peer = connection.peer
        auth_deadline = anyio.current_time() + idle_timeout_s
        while True:
            # Until it authenticates, a connection has one idle timeout in all to do so (a
            # byte now and then does not keep a stranger's connection open).
            timeout = idle_timeout_s
            if not connection.trusted:
                timeout = min(timeout, auth_deadline - anyio.current_time())
            try:
                with anyio.fail_after(max(timeout, 0.0)):
                    data = await connection.receive(_READ_CHUNK)
            except TimeoutError as exc:
                silent = f"peer {peer} silent or unauthenticated for {idle_timeout_s} s"
                raise LinkClosed(self.label, silent) from exc
            except (anyio.EndOfStream, anyio.BrokenResourceError) as exc:
                raise LinkClosed(self.label, f"peer {peer} closed the stream") from exc
            self.on_data(self.label, peer, data)


class TcpClientLink(_StreamLink):
    """TCP client: connects, reads, and on any failure reconnects with jittered backoff."""

    def __init__(self, config: LinkConfig, on_data: DataHandler, on_close: CloseHandler) -> None:
        super().__init__(config, on_data, on_close)
        self._connection: Connection | None = None

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
                    connection = await connect(ep.host, ep.port)
            except (OSError, TimeoutError) as exc:
                reason = f"connect failed: {os_reason(exc) or 'timed out'}"
                if self.reason != reason:
                    self.log.warning("link_connect_failed", uri=str(ep), error=reason)
                self.state, self.reason = "reconnecting", reason
            else:
                self.connects += 1
                self.state, self.reason = "connected", ""
                self.log.info("link_connected", uri=str(ep))
                delay = self.config.reconnect_initial_s
                if not started:
                    task_status.started()
                    started = True
                connection.trusted = True  # the peer we chose to connect to
                self._connection = connection
                try:
                    with connection.sock:
                        await self._pump(connection)
                except LinkClosed as exc:
                    self.state, self.reason = "reconnecting", str(exc)
                    self.log.warning("link_closed", uri=str(ep))
                finally:
                    self._connection = None
                    self.on_close(self.label, connection.peer)
            if not started:
                task_status.started()
                started = True
            await anyio.sleep(delay * random.uniform(0.5, 1.0))  # noqa: S311 - jitter
            delay = min(delay * 2, self.config.reconnect_max_s)

    async def send(self, data: bytes) -> None:
        connection = self._connection
        if connection is None:
            raise LinkUnavailable(self.label, "not connected")
        try:
            await connection.send(data)
        except anyio.BrokenResourceError as exc:
            raise LinkUnavailable(self.label, f"send failed: {exc}") from exc


class TcpServerLink(_StreamLink):
    """TCP server: each accepted connection is a peer with its own parser.

    At most ``max_connections`` at once (``gateway.transports.listener``: a new connection evicts
    one that has not authenticated, else it is closed). A connection must authenticate a frame
    within ``idle_timeout_s`` and then stay heard within it, or it is closed; one that sends only
    frames failing authentication is hung up on by ingest (``drop``). Connects and closes of peers
    that never authenticated are counted, not logged one by one.
    """

    def __init__(self, config: LinkConfig, on_data: DataHandler, on_close: CloseHandler) -> None:
        super().__init__(config, on_data, on_close)
        self._streams: dict[object, Connection] = {}
        self.local_port = 0
        self.idle_timeout_s = config.idle_timeout_s
        self._listener = TcpListener(
            config.uri.host,
            config.uri.port,
            name=self.label,
            what=f"link {self.label}",
            max_connections=config.max_connections,
        )
        self.stats = self._listener.stats

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        self.local_port = self._listener.bind()
        self.is_bound, self.state = True, "listening"
        self.log.info("link_bound", uri=str(self.endpoint), port=self.local_port)
        task_status.started()
        try:
            await self._listener.run(self._serve)
        finally:
            self.is_bound, self.state = False, "closed"

    async def _serve(self, connection: Connection) -> None:
        peer = connection.peer
        self.connects += 1
        self._streams[peer] = connection
        try:
            await self._pump(connection, idle_timeout_s=self.idle_timeout_s)
        except LinkClosed as exc:
            if connection.trusted:
                self.log.info("link_peer_closed", peer=f"{peer[0]}:{peer[1]}", reason=str(exc))
        finally:
            self._streams.pop(peer, None)
            self.on_close(self.label, peer)

    def trust(self, peer: object) -> None:
        connection = self._streams.get(peer)
        if connection is not None and not connection.trusted:
            connection.trusted = True
            self.log.info(
                "link_peer_authenticated", peer=f"{connection.peer[0]}:{connection.peer[1]}"
            )

    def drop(self, peer: object) -> None:
        connection = self._streams.get(peer)
        if connection is not None:
            connection.close()

    async def send(self, data: bytes) -> None:
        if not self._streams:
            raise LinkUnavailable(self.label, "no peer connected")
        for connection in list(self._streams.values()):
            await connection.send(data)

    async def send_to(self, peer: object, data: bytes) -> None:
        connection = self._streams.get(peer)
        if connection is None:
            raise LinkUnavailable(self.label, "the authenticated peer is no longer connected")
        try:
            await connection.send(data)
        except anyio.BrokenResourceError as exc:
            raise LinkUnavailable(self.label, f"send failed: {exc}") from exc

    def status(self) -> dict[str, object]:
        return {**super().status(), "connections": self.stats.status()}


class SerialLink(Link):
    """A serial device (radio modem), read without a thread through the event loop.

    A device missing at start, or lost while running (a USB radio unplugged), degrades this
    link only: it reports started at once (readiness does not wait on hardware), shows
    ``waiting for device`` with the reason on /status, and reopens the device with jittered
    backoff up to ``reconnect_max_s``. No other link or airframe is affected.
    """

    def __init__(self, config: LinkConfig, on_data: DataHandler, on_close: CloseHandler) -> None:
        super().__init__(config, on_data, on_close)
        self._fd: int | None = None

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        ep = self.endpoint
        delay = self.config.reconnect_initial_s
        self.is_bound = True  # like a client: nothing to bind, readiness does not wait
        task_status.started()
        while True:
            try:
                fd = open_raw(ep.device, ep.baud)  # raw 8N1: nothing touches MAVLink bytes
            except OSError as exc:
                reason = f"cannot open {ep.device}: {os_reason(exc)}"
                if self.reason != reason:
                    self.log.warning("link_device_unavailable", device=ep.device, error=reason)
                self.state, self.reason = "waiting for device", reason
            else:
                self.connects += 1
                self.state, self.reason = "open", ""
                self.log.info("link_bound", uri=str(ep))
                delay = self.config.reconnect_initial_s
                try:
                    await self._read(fd)
                except LinkClosed as exc:
                    self.state, self.reason = "waiting for device", str(exc)
                    self.log.warning("link_device_lost", device=ep.device, error=str(exc))
            await anyio.sleep(delay * random.uniform(0.5, 1.0))  # noqa: S311 - jitter
            delay = min(delay * 2, self.config.reconnect_max_s)

    async def _read(self, fd: int) -> None:
        peer = self.endpoint.device
        self._fd = fd
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
            self._fd = None
            os.close(fd)

    async def send(self, data: bytes) -> None:
        fd = self._fd
        if fd is None:
            raise LinkUnavailable(self.label, f"not open ({self.reason or self.state})")
        view = memoryview(data)
        while view:
            await anyio.wait_writable(fd)
            try:
                written = os.write(fd, view)
            except BlockingIOError:
                continue
            except OSError as exc:
                raise LinkUnavailable(self.label, f"write failed: {exc.strerror}") from exc
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
