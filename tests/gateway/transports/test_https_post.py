"""The HTTPS client the gute2 and slb sinks share: one deadline for the whole exchange."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import anyio
import pytest
from anyio.streams.buffered import BufferedByteReceiveStream
from anyio.streams.tls import TLSStream
from gute_peer import GutePeer
from https_peer import MAX_HEAD_BYTES, Answer, Head

from gateway.contract import sample_events
from gateway.events import EventKind, Handoff
from gateway.transports.httpspost import HttpsPoster
from gateway.transports.tls import TlsFiles
from sinks.gute2.codec import encode_handoff

SAMPLE = sample_events(frozenset({EventKind.HANDOFF}))[0]
assert isinstance(SAMPLE, Handoff)


class TricklingPeer(GutePeer):
    """Answers every request with a status line, then one header byte every 0.2 s, forever."""

    async def _exchange(self, reader: BufferedByteReceiveStream, stream: TLSStream) -> bool:
        await reader.receive_until(b"\r\n\r\n", MAX_HEAD_BYTES)
        await stream.send(b"HTTP/1.1 200 OK\r\n")
        while True:
            await stream.send(b"X")
            await anyio.sleep(0.2)

    def _answer(self, head: Head, body: bytes) -> Answer:  # pragma: no cover - never reached
        return 200, {}


@pytest.mark.anyio
async def test_a_server_trickling_its_answer_is_cut_off_at_the_deadline(tmp_path: Path) -> None:
    """httpx's read timeout restarts with every byte; the poster's deadline does not."""
    async with TricklingPeer(tmp_path) as peer:
        tls = peer.tls_options()
        files = TlsFiles(Path(tls["ca_file"]), Path(tls["cert_file"]), Path(tls["key_file"]))
        poster = HttpsPoster("gute", peer.url, files, timeout_s=1.0, max_in_flight=2)
        try:
            outcomes = await poster.post_all([SAMPLE], lambda _: b"{}")
        finally:
            await poster.aclose()
    (outcome,) = outcomes
    assert outcome.result == "retry"
    assert outcome.detail == f"{peer.url}: no answer within 1.0 s"


@pytest.mark.anyio
async def test_a_document_the_encoder_refuses_is_refused_without_a_request(
    tmp_path: Path,
) -> None:
    def refuse(_: Handoff) -> bytes:
        raise ValueError("no JSON for a NaN")

    async with GutePeer(tmp_path) as peer:
        tls = peer.tls_options()
        files = TlsFiles(Path(tls["ca_file"]), Path(tls["cert_file"]), Path(tls["key_file"]))
        poster = HttpsPoster("gute", peer.url, files, timeout_s=5.0, max_in_flight=2)
        try:
            (outcome,) = await poster.post_all([SAMPLE], refuse)
        finally:
            await poster.aclose()
        assert peer.requests == []
    assert (outcome.event_id, outcome.result, outcome.detail) == (
        SAMPLE.event_id,
        "refused",
        "no JSON for a NaN",
    )


@pytest.mark.anyio
async def test_a_batch_is_posted_event_by_event_and_only_the_refused_one_is_refused(
    tmp_path: Path,
) -> None:
    second = SAMPLE.model_copy(update={"event_id": f"{SAMPLE.handoff_id}-r1", "revision": 1})

    def encode(handoff: Handoff) -> bytes:
        if handoff is second:
            raise ValueError("no JSON for a NaN")
        return encode_handoff(handoff)

    async with GutePeer(tmp_path) as peer:
        tls = peer.tls_options()
        files = TlsFiles(Path(tls["ca_file"]), Path(tls["cert_file"]), Path(tls["key_file"]))
        poster = HttpsPoster("gute", peer.url, files, timeout_s=5.0, max_in_flight=2)
        try:
            outcomes = await poster.post_all([SAMPLE, second], encode)
        finally:
            await poster.aclose()
        assert list(peer.accepted) == [SAMPLE.event_id]
    assert sorted((o.event_id, o.result) for o in outcomes) == [
        (SAMPLE.event_id, "delivered"),
        (second.event_id, "refused"),
    ]


def test_httpcore_learns_its_event_loop_without_a_failed_import_each_time() -> None:
    """httpcore imports sniffio on every lock and shield of a request; were it missing, each
    import would fail after a search of sys.path (~30 µs, several per POST): pyproject lists
    it since anyio 4 no longer brings it."""
    assert importlib.util.find_spec("sniffio") is not None
