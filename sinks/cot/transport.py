"""Where CoT goes: UDP (mesh, multicast or unicast) and TAK server streams (TCP and TLS).

Both transports are driven from the sink's calls (``open``, ``send``, ``aclose``) and, for the
mesh announcements, from the sink's ``run`` lifetime, which the SinkRunner starts in its own
task group: nothing here starts a task, so no task group outlives a call and the runner's
deadlines and cancel scopes nest as they should. Sockets are non-blocking and every wait goes
through ``anyio.wait_readable``/``wait_writable``; the caller's deadline bounds each call.
UDP is in ``sinks.cot.udp``.

A stream reads what the server sent at the start of every call: that is how it notices a
server that hung up (EOF leads to one immediate reconnect), drains the events a TAK server
relays from other clients, and follows the TAK protocol v1 negotiation (``cot.md`` §7): after
the server's ``TakControl`` offer of version 1 it sends a ``TakRequest`` and sends nothing
else until the ``TakResponse``; ``status="true"`` switches both directions to protobuf stream
framing, anything else keeps XML. A server that offers nothing stays on XML. A response that
does not come within ``response_wait_s`` (≥ 1 min by the spec) ends the connection and the
destination stays on XML from then on. A write cut short (error or cancellation) closes the
connection, since half a frame would corrupt everything after it.
"""

from __future__ import annotations

import socket
import ssl
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Literal

import anyio
import structlog

from gateway.errors import TransientSinkError
from gateway.transports.stream import open_tcp, send_all, start_tls
from gateway.transports.tls import TlsFiles, describe_tls_error, tls_context
from sinks.cot.codec import Encoded, Encoding, cot_time
from sinks.cot.validate import TakControl, scan_control

__all__ = ["Endpoint", "StreamConnection"]

log = structlog.get_logger(__name__)

Protocol = Literal["xml", "protobuf", "negotiate"]
_END = b"</event>"
_MAX_INBOX = 1 << 20
_READ_CHUNK = 65_536


@dataclass(frozen=True, slots=True)
class Endpoint:
    """One validated destination, as the transports need it."""

    uri: str
    scheme: Literal["udp", "udp+multicast", "tcp", "tls"]
    host: str
    port: int
    protocol: Protocol = "xml"
    ttl: int = 1
    interface: str | None = None
    tls: TlsFiles | None = None
    server_hostname: str | None = None


class _PeerClosed(Exception):
    """The server closed the stream."""


class StreamConnection:
    """A TAK server stream over TCP or TLS, with the TAK protocol v1 negotiation."""

    def __init__(
        self,
        endpoint: Endpoint,
        sink: str,
        *,
        connect_timeout_s: float,
        offer_wait_s: float,
        response_wait_s: float,
    ) -> None:
        self.endpoint = endpoint
        self.sink = sink
        self.connect_timeout_s = connect_timeout_s
        self.offer_wait_s = offer_wait_s
        self.response_wait_s = response_wait_s
        self.may_negotiate = endpoint.protocol == "negotiate"
        self.mode: Literal["xml", "requested", "protobuf"] = "xml"
        self._sock: socket.socket | None = None
        self._inbox = bytearray()
        self._offer_deadline: float | None = None
        self._response_deadline = 0.0
        self._context: ssl.SSLContext | None = None
        self.log = log.bind(sink=sink, destination=endpoint.uri)

    @property
    def is_connected(self) -> bool:
        """Whether a connection is open (it may still be negotiating)."""
        return self._sock is not None

    def _fail(self, what: str) -> TransientSinkError:
        return TransientSinkError(f"sink {self.sink}: {self.endpoint.uri}: {what}", sink=self.sink)

    # -- connecting --------------------------------------------------------------------------

    async def _tcp_socket(self) -> socket.socket:
        return await open_tcp(self.endpoint.host, self.endpoint.port)

    async def _handshake(self, raw: socket.socket) -> socket.socket:
        tls = self.endpoint.tls
        if tls is None:
            return raw
        if self._context is None:
            self._context = tls_context(tls)
        hostname = self.endpoint.server_hostname or self.endpoint.host
        return await start_tls(raw, self._context, hostname)

    async def _connect(self) -> None:
        hostname = self.endpoint.server_hostname or self.endpoint.host
        raw: socket.socket | None = None
        try:
            with anyio.fail_after(self.connect_timeout_s):
                raw = await self._tcp_socket()
                sock = await self._handshake(raw)
        except TimeoutError:
            self._discard(raw)
            raise self._fail(f"no connection within {self.connect_timeout_s} s") from None
        except ssl.SSLError as exc:
            self._discard(raw)
            tls = self.endpoint.tls
            assert tls is not None  # noqa: S101 - only TLS raises SSLError
            raise self._fail(describe_tls_error(exc, tls, hostname)) from exc
        except (OSError, ValueError) as exc:
            self._discard(raw)
            raise self._fail(f"cannot connect: {exc}") from exc
        except BaseException:
            self._discard(raw)
            raise
        self._sock, self.mode = sock, "xml"
        self._inbox.clear()
        self._offer_deadline = (
            anyio.current_time() + self.offer_wait_s if self.may_negotiate else None
        )
        self.log.info("cot_destination_connected", tls=self.endpoint.tls is not None)

    @staticmethod
    def _discard(sock: socket.socket | None) -> None:
        if sock is not None:
            sock.close()

    def _close(self) -> None:
        self._discard(self._sock)
        self._sock, self.mode, self._offer_deadline = None, "xml", None
        self._inbox.clear()

    # -- reading -----------------------------------------------------------------------------

    def _receive_now(self) -> None:
        """Take what the server sent, without waiting; ``_PeerClosed`` at EOF."""
        assert self._sock is not None  # noqa: S101 - connected
        for _ in range(_MAX_INBOX // _READ_CHUNK):
            try:
                chunk = self._sock.recv(_READ_CHUNK)
            except (BlockingIOError, ssl.SSLWantReadError, ssl.SSLWantWriteError):
                return
            if not chunk:
                raise _PeerClosed
            if self.mode != "protobuf":  # protobuf from the server is relayed traffic: dropped
                self._inbox += chunk

    async def _process(self) -> None:
        """Act on the control events in the inbox; drop everything else."""
        while self.mode != "protobuf" and (end := self._inbox.find(_END)) >= 0:
            chunk = bytes(self._inbox[: end + len(_END)])
            del self._inbox[: end + len(_END)]
            control = scan_control(chunk)
            if control is TakControl.OFFER_V1 and self.mode == "xml" and self.may_negotiate:
                await self._request()
            elif control in (TakControl.ACCEPTED, TakControl.REFUSED) and self.mode == "requested":
                self._settle(control is TakControl.ACCEPTED)
        if self.mode == "protobuf" or len(self._inbox) > _MAX_INBOX:
            self._inbox.clear()

    def _settle(self, accepted: bool) -> None:
        self.mode = "protobuf" if accepted else "xml"
        self.may_negotiate = accepted
        self._offer_deadline = None
        self.log.info("tak_protocol_negotiated", protobuf=accepted)

    async def _request(self) -> None:
        now = datetime.now(UTC)
        stale = cot_time(now + timedelta(minutes=1))
        request = (
            '<?xml version="1.0" encoding="UTF-8" standalone="yes"?>\n'
            f'<event version="2.0" uid="{self.sink}-takp-request" type="t-x-takp-q" how="m-g" '
            f'time="{cot_time(now)}" start="{cot_time(now)}" stale="{stale}">'
            '<point lat="0.0" lon="0.0" hae="0.0" ce="9999999.0" le="9999999.0"/>'
            '<detail><TakControl><TakRequest version="1"/></TakControl></detail></event>'
        )
        await self._write(request.encode())
        self.mode = "requested"
        self._offer_deadline = None
        self._response_deadline = anyio.current_time() + self.response_wait_s

    async def _wait_readable_until(self, deadline: float) -> None:
        assert self._sock is not None  # noqa: S101 - connected
        pending = isinstance(self._sock, ssl.SSLSocket) and self._sock.pending()
        if not pending:
            with anyio.move_on_after(max(0.0, deadline - anyio.current_time())):
                await anyio.wait_readable(self._sock)
        self._receive_now()
        await self._process()

    async def _ready(self) -> None:
        """Connected, caught up with the server, and not waiting on the negotiation."""
        if self._sock is None:
            await self._connect()
        try:
            self._receive_now()
        except _PeerClosed:
            self.log.warning("cot_destination_closed", reason="the server closed the stream")
            self._close()
            await self._connect()
        await self._process()
        while self._offer_deadline is not None and anyio.current_time() < self._offer_deadline:
            await self._wait_readable_until(self._offer_deadline)
        self._offer_deadline = None
        while self.mode == "requested":
            if anyio.current_time() >= self._response_deadline:
                self.may_negotiate = False
                self._close()
                self.log.warning("tak_protocol_fallback", reason="no TakResponse")
                raise self._fail(
                    f"no TakResponse within {self.response_wait_s} s; staying on XML from now on"
                )
            await self._wait_readable_until(self._response_deadline)

    # -- writing -----------------------------------------------------------------------------

    async def _write(self, data: bytes) -> None:
        assert self._sock is not None  # noqa: S101 - connected
        done = False
        try:
            await send_all(self._sock, data)
            done = True
        finally:
            if not done:
                self._close()  # a partial frame would corrupt the stream

    async def open(self) -> None:
        """Connect (and negotiate) if not connected; ``TransientSinkError`` on failure."""
        await self._guarded(None)

    async def send(self, events: Sequence[Encoded]) -> None:
        """Write ``events`` back to back in the negotiated framing; ``TransientSinkError``."""
        await self._guarded(events)

    async def _guarded(self, events: Sequence[Encoded] | None) -> None:
        try:
            await self._ready()
            if events:
                encoding: Encoding = "stream" if self.mode == "protobuf" else "xml"
                await self._write(b"".join(e.get(encoding) for e in events))
        except (_PeerClosed, OSError) as exc:
            self._close()
            if isinstance(exc, ssl.SSLError) and self.endpoint.tls is not None:
                hostname = self.endpoint.server_hostname or self.endpoint.host
                raise self._fail(describe_tls_error(exc, self.endpoint.tls, hostname)) from exc
            reason = "the server closed the stream" if isinstance(exc, _PeerClosed) else str(exc)
            raise self._fail(f"connection lost: {reason}") from exc

    async def aclose(self) -> None:
        """Close the connection."""
        self._close()
