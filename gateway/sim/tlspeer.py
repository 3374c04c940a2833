"""The demo's TLS stand-in peers' listener: loopback, the demo CA, a client certificate required.

A subclass gives ``_connection(stream)``; ``port`` is bound when the peer is made, so the
gateway's config can name it before ``serve`` runs.
"""

from __future__ import annotations

import socket
import ssl

import anyio
import anyio.abc
from anyio.streams.tls import TLSListener

from gateway.sim.pki import DemoPki

__all__ = ["TlsPeer"]


class TlsPeer:
    """A TLS listener on a loopback port that takes only clients the demo CA signed."""

    def __init__(self, pki: DemoPki) -> None:
        self._context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH, cafile=pki.ca_file)
        self._context.load_cert_chain(pki.server_cert, pki.server_key)
        self._context.verify_mode = ssl.CERT_REQUIRED
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._socket.bind(("127.0.0.1", 0))
        self._socket.listen(16)
        self.port = int(self._socket.getsockname()[1])

    async def serve(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Accept connections until cancelled."""
        tcp = await anyio.abc.SocketListener.from_socket(self._socket)
        listener = TLSListener(tcp, self._context, standard_compatible=False)
        task_status.started()
        async with listener:
            await listener.serve(self._connection)

    async def _connection(self, stream: anyio.abc.ByteStream) -> None:
        raise NotImplementedError
