"""TCP and TLS client streams on non-blocking sockets, for links and sinks alike.

``open_tcp`` resolves and connects without blocking the loop (every address of the name in
turn), with keep-alive and no Nagle delay; ``start_tls`` runs the TLS handshake on it with a
context from ``gateway.transports.tls`` (CA pinned, hostname verified). The caller's deadline
bounds both. ``send_all`` writes a buffer whole on either kind of socket. The fleet's TCP
client links, the CoT sink's TAK server streams and the NFFI sink's IP1 stream use them.
"""

from __future__ import annotations

import errno
import os
import socket
import ssl

import anyio

__all__ = ["open_tcp", "send_all", "start_tls"]


async def open_tcp(host: str, port: int) -> socket.socket:
    """A connected non-blocking TCP socket to ``host:port``; ``OSError`` if none connects."""
    infos = await anyio.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    error: OSError = OSError(errno.EHOSTUNREACH, f"no address for {host}")
    for family, kind, proto, _, address in infos:
        sock = socket.socket(family, kind, proto)
        connected = False
        try:
            sock.setblocking(False)
            code = sock.connect_ex(address)
            if code in (errno.EINPROGRESS, errno.EAGAIN):
                await anyio.wait_writable(sock)
                code = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if code:
                raise OSError(code, os.strerror(code))
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            connected = True
            return sock
        except OSError as exc:
            error = exc
        finally:
            if not connected:
                sock.close()
    raise error


async def start_tls(raw: socket.socket, context: ssl.SSLContext, hostname: str) -> ssl.SSLSocket:
    """Wrap ``raw`` and complete the TLS handshake; ``ssl.SSLError`` if the peer is refused.

    On failure the socket is closed (the wrapped socket owns the descriptor).
    """
    sock = context.wrap_socket(raw, server_hostname=hostname, do_handshake_on_connect=False)
    done = False
    try:
        while not done:
            try:
                sock.do_handshake()
                done = True
            except ssl.SSLWantReadError:
                await anyio.wait_readable(sock)
            except ssl.SSLWantWriteError:
                await anyio.wait_writable(sock)
    finally:
        if not done:
            sock.close()
    return sock


async def send_all(sock: socket.socket, data: bytes) -> None:
    """Write ``data`` whole on the non-blocking ``sock`` (plain or TLS), waiting as it asks.

    Raises ``OSError`` (``ssl.SSLError`` included) if the peer fails; how much of ``data`` was
    written is then unknown, so a framed stream must be closed by the caller.
    """
    view = memoryview(data)
    while view:
        try:
            view = view[sock.send(view) :]
        except (BlockingIOError, ssl.SSLWantWriteError):
            await anyio.wait_writable(sock)
        except ssl.SSLWantReadError:
            await anyio.wait_readable(sock)
