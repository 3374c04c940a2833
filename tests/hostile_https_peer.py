"""A hostile HTTPS battery for tests: real TLS with client certificates, scripted answers.

``ScriptedPeer`` is an ``https_peer.HttpsPeer`` whose answers are scripts: each POST takes the
next ``Script`` of ``scripts`` (a list of byte strings sent one after another, with an optional
pause between them, then the connection is kept, or closed), and once they are used up it
answers ``201`` honestly and records the key in ``accepted`` (a key at most once; again: 409).
It counts the TLS connections it accepted (``connections``) and every request's
``Idempotency-Key`` in arrival order (``keys``).

The scripts in ``HOSTILE`` are what a broken or hostile battery can send back.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import anyio
from anyio.streams.buffered import BufferedByteReceiveStream
from anyio.streams.tls import TLSStream
from https_peer import MAX_HEAD_BYTES, Answer, Head, HttpsPeer, parse_head

__all__ = ["HOSTILE", "Script", "ScriptedPeer", "chunked"]


@dataclass(frozen=True)
class Script:
    """What one answer is: ``parts`` sent ``pause_s`` apart, then ``close`` or keep."""

    name: str
    parts: tuple[bytes, ...] = ()
    pause_s: float = 0.0
    close: bool = True
    #: Before answering, wait this long (a server closing a kept connection, racing us).
    delay_s: float = 0.0


def chunked(body: bytes, size: int = 7) -> bytes:
    """``body`` as a chunked transfer coding, ``size`` bytes a chunk."""
    out = b"".join(
        b"%x\r\n%s\r\n" % (len(body[i : i + size]), body[i : i + size])
        for i in range(0, len(body), size)
    )
    return out + b"0\r\n\r\n"


#: The answers of a broken or hostile battery, one per POST.
HOSTILE = [
    Script("garbage", (b"SSH-2.0-OpenSSH_9.6\r\n\r\n",)),
    Script("huge head", (b"HTTP/1.1 201 Created\r\nX-Pad: " + b"a" * 40_000 + b"\r\n\r\n",)),
    Script(
        "many headers",
        (b"HTTP/1.1 201 Created\r\n" + b"".join(b"X-%d: 1\r\n" % n for n in range(500)) + b"\r\n",),
    ),
    Script(
        "closed mid-answer",
        (b'HTTP/1.1 201 Created\r\nContent-Length: 100\r\n\r\n{"sta',),
    ),
    Script("bad chunk", (b"HTTP/1.1 201 Created\r\nTransfer-Encoding: chunked\r\n\r\nZZ\r\n",)),
    Script("trickle", (b"HTTP/1.1 201 Created\r\n",) + (b"X",) * 200, pause_s=0.05),
]


class ScriptedPeer(HttpsPeer):
    """Answers POSTs by script first, then honestly (201, chunked)."""

    def __init__(self, directory: Path, scripts: list[Script] | None = None) -> None:
        super().__init__(directory, file_prefix="hostile")
        self.scripts = list(scripts or [])
        self.connections = 0
        self.keys: list[str] = []
        self.accepted: dict[str, bytes] = {}
        #: The scripts played, in order.
        self.played: list[str] = []

    @property
    def url(self) -> str:
        """Where the cues go."""
        return f"https://127.0.0.1:{self.port}/gute2/handoffs"

    async def _serve(self, raw: anyio.abc.ByteStream, context: object) -> None:  # type: ignore[override]
        self.connections += 1
        await super()._serve(raw, context)  # type: ignore[arg-type]

    async def _exchange(self, reader: BufferedByteReceiveStream, stream: TLSStream) -> bool:
        head: Head = parse_head(await reader.receive_until(b"\r\n\r\n", MAX_HEAD_BYTES))
        length = int(head.headers.get("content-length", "0"))
        body = await reader.receive_exactly(length) if length else b""
        key = head.headers.get("idempotency-key", "")
        self.keys.append(key)
        if self.scripts:
            script = self.scripts.pop(0)
            self.played.append(script.name)
            await anyio.sleep(script.delay_s)
            for n, part in enumerate(script.parts):
                if n and script.pause_s:
                    await anyio.sleep(script.pause_s)
                await stream.send(part)
            return not script.close
        status = 409 if key in self.accepted else 201
        self.accepted.setdefault(key, body)
        answer = json.dumps({"status": "accepted", "handoff_id": key}).encode()
        await stream.send(
            b"HTTP/1.1 %d Created\r\nContent-Type: application/json\r\n"
            b"Transfer-Encoding: chunked\r\n\r\n" % status + chunked(answer)
        )
        return True

    def _answer(self, head: Head, body: bytes) -> Answer:  # pragma: no cover - never called
        return 500, {}
