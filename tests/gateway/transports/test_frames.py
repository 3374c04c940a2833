"""Length-prefixed frames (gateway.transports.frames) on real loopback sockets and real TLS."""

from __future__ import annotations

import socket
import ssl
import struct
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager

import anyio
import anyio.abc
import pytest
import trustme
from anyio.streams.tls import TLSListener

from gateway.errors import LinkClosed, Malformed, Oversize
from gateway.transports.frames import KEEPALIVE_IDLE_S, FrameStream, connect_tls

Serve = Callable[[anyio.abc.ByteStream], Awaitable[None]]


@asynccontextmanager
async def server(serve: Serve) -> AsyncIterator[int]:
    """A TCP server on loopback running ``serve`` per connection; yields its port."""
    listener = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=0)
    async with listener, anyio.create_task_group() as tg:
        tg.start_soon(listener.serve, serve)
        yield int(listener.extra(anyio.abc.SocketAttribute.local_port))
        tg.cancel_scope.cancel()


def sends(*chunks: bytes) -> Serve:
    """A server that writes ``chunks`` and hangs up."""

    async def serve(stream: anyio.abc.ByteStream) -> None:
        async with stream:
            for chunk in chunks:
                await stream.send(chunk)

    return serve


def frame(payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + payload


async def frames_from(port: int, max_frame_bytes: int = 1024) -> FrameStream:
    stream = await anyio.connect_tcp("127.0.0.1", port)
    return FrameStream(stream, max_frame_bytes=max_frame_bytes, link="test")


class TestReceive:
    """One whole frame at a time, within the bound; every way it can end is told apart."""

    @pytest.mark.anyio
    async def test_frames_split_and_joined_arbitrarily_are_read_whole(self) -> None:
        wire = frame(b"<a/>") + frame(b"") + frame(b"x" * 1000)
        async with server(sends(wire[:3], wire[3:9], wire[9:])) as port:
            frames = await frames_from(port)
            with anyio.fail_after(5):
                got = [await frames.receive() for _ in range(3)]
                with pytest.raises(LinkClosed, match="closed the connection"):
                    await frames.receive()
            await frames.aclose()
        assert got == [b"<a/>", b"", b"x" * 1000]

    @pytest.mark.anyio
    async def test_an_oversize_length_is_refused_without_reading_it(self) -> None:
        async with server(sends(struct.pack(">I", 1 << 31), b"y" * 64)) as port:
            frames = await frames_from(port)
            with anyio.fail_after(5), pytest.raises(Oversize) as caught:
                await frames.receive()
            await frames.aclose()
        assert (caught.value.size, caught.value.limit, caught.value.reason) == (
            1 << 31,
            1024,
            "oversize",
        )

    @pytest.mark.anyio
    @pytest.mark.parametrize("wire", [b"\x00\x00", frame(b"abcdef")[:7]], ids=["header", "body"])
    async def test_a_hang_up_inside_a_frame_is_malformed(self, wire: bytes) -> None:
        async with server(sends(wire)) as port:
            frames = await frames_from(port)
            with anyio.fail_after(5), pytest.raises(Malformed, match="inside a frame"):
                await frames.receive()
            await frames.aclose()

    @pytest.mark.anyio
    async def test_a_receive_cut_short_loses_nothing(self) -> None:
        """Cancelled half way through a frame, the next receive still gets it whole."""
        release = anyio.Event()

        async def slow(stream: anyio.abc.ByteStream) -> None:
            async with stream:
                await stream.send(frame(b"hello world")[:6])
                await release.wait()
                await stream.send(frame(b"hello world")[6:])

        async with server(slow) as port:
            frames = await frames_from(port)
            with anyio.move_on_after(0.2) as scope:
                await frames.receive()
            assert scope.cancelled_caught
            release.set()
            with anyio.fail_after(5):
                assert await frames.receive() == b"hello world"
            await frames.aclose()

    @pytest.mark.anyio
    async def test_sending_more_than_the_bound_is_refused(self) -> None:
        async with server(sends()) as port:
            frames = await frames_from(port, max_frame_bytes=16)
            with pytest.raises(Oversize):
                await frames.send(b"z" * 17)
            await frames.aclose()


class TestTls:
    """connect_tls: the pinned CA, the hostname, keep-alive."""

    @pytest.mark.anyio
    async def test_frames_over_tls_with_keepalive_probes_set(self) -> None:
        ca = trustme.CA()
        server_context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        ca.issue_cert("127.0.0.1").configure_cert(server_context)
        client_context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH)
        ca.configure_trust(client_context)
        received: list[bytes] = []

        async def echo(stream: anyio.abc.ByteStream) -> None:
            async with stream:
                framed = FrameStream(stream, max_frame_bytes=64, link="server")
                payload = await framed.receive()
                received.append(payload)
                await framed.send(payload[::-1])

        tcp = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=0)
        port = int(tcp.extra(anyio.abc.SocketAttribute.local_port))
        listener = TLSListener(tcp, server_context, standard_compatible=False)
        async with listener, anyio.create_task_group() as tg:
            tg.start_soon(listener.serve, echo)
            with anyio.fail_after(5):
                stream = await connect_tls("127.0.0.1", port, client_context, "127.0.0.1")
                sock = stream.extra(anyio.abc.SocketAttribute.raw_socket)
                if hasattr(socket, "TCP_KEEPIDLE"):
                    idle = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE)
                    assert idle == KEEPALIVE_IDLE_S
                assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE)
                frames = FrameStream(stream, max_frame_bytes=64, link="client")
                await frames.send(b"ping")
                assert await frames.receive() == b"gnip"
                await frames.aclose()
                with pytest.raises(ssl.SSLCertVerificationError):
                    await connect_tls("127.0.0.1", port, client_context, "gute.example")
            tg.cancel_scope.cancel()
        assert received == [b"ping"]
