"""The HTTP/1.1 client of HttpsPoster against a scripted, hostile HTTPS battery on loopback."""

from __future__ import annotations

import ssl
from pathlib import Path

import anyio
import pytest
from hostile_https_peer import HOSTILE, Script, ScriptedPeer

from gateway.contract import sample_events
from gateway.events import EventKind, Handoff
from gateway.testing import eventually
from gateway.transports.http1 import MAX_HEAD_BYTES, MAX_HEADERS, Http1Origin
from gateway.transports.httpspost import MAX_REASON_BYTES, HttpsPoster
from gateway.transports.tls import TlsFiles

SAMPLE = sample_events(frozenset({EventKind.HANDOFF}))[0]
assert isinstance(SAMPLE, Handoff)

OK_KEPT = Script(
    "201, kept", (b"HTTP/1.1 201 Created\r\nContent-Length: 2\r\n\r\n{}",), close=False
)


def handoff(n: int) -> Handoff:
    return SAMPLE.model_copy(update={"event_id": f"H-{n}", "handoff_id": f"H-{n}"})


def poster_for(peer: ScriptedPeer, timeout_s: float = 5.0) -> HttpsPoster:
    files = TlsFiles(peer.ca_file, peer.cert_file, peer.key_file)
    return HttpsPoster("gute", peer.url, files, timeout_s=timeout_s, max_in_flight=2)


async def post(poster: HttpsPoster, n: int) -> tuple[str, str]:
    (outcome,) = await poster.post_all([handoff(n)], lambda _: b"{}")
    return outcome.result, outcome.detail


class TestKeptConnections:
    """One TLS connection carries POST after POST; one the server closed is never reused."""

    @pytest.mark.anyio
    async def test_posts_share_one_connection_and_chunked_answers_are_read(
        self, tmp_path: Path
    ) -> None:
        with anyio.fail_after(20):
            async with ScriptedPeer(tmp_path) as peer:
                poster = poster_for(peer)
                try:
                    results = [await post(poster, n) for n in range(3)]
                finally:
                    await poster.aclose()
        assert results == [("delivered", "")] * 3
        assert peer.connections == 1
        assert peer.keys == ["H-0", "H-1", "H-2"]

    @pytest.mark.anyio
    async def test_a_connection_the_server_closed_after_answering_is_not_reused(
        self, tmp_path: Path
    ) -> None:
        answered_then_closed = Script("201, then closed", OK_KEPT.parts, close=True)
        with anyio.fail_after(20):
            async with ScriptedPeer(tmp_path, [answered_then_closed]) as peer:
                poster = poster_for(peer)
                try:
                    first = await post(poster, 1)
                    client = poster._client
                    assert isinstance(client, Http1Origin)
                    await eventually(lambda: not any(w.idle_and_open for w in client._idle))
                    second = await post(poster, 2)
                finally:
                    await poster.aclose()
        assert [first, second] == [("delivered", ""), ("delivered", "")]
        assert peer.keys == ["H-1", "H-2"]  # nothing was written to the closed connection
        assert peer.connections == 2

    @pytest.mark.anyio
    async def test_a_post_a_kept_connection_lost_unanswered_is_sent_once_more(
        self, tmp_path: Path
    ) -> None:
        """The server read the POST and closed without a word: it may have processed it, so
        the copy on a new connection carries the same Idempotency-Key (a 409 at worst)."""
        read_then_closed = Script("read, then closed", ())
        with anyio.fail_after(20):
            async with ScriptedPeer(tmp_path, [OK_KEPT, read_then_closed]) as peer:
                poster = poster_for(peer)
                try:
                    results = [await post(poster, 1), await post(poster, 2)]
                finally:
                    await poster.aclose()
        assert results == [("delivered", ""), ("delivered", "")]
        assert peer.keys == ["H-1", "H-2", "H-2"]
        assert peer.connections == 2
        assert list(peer.accepted) == ["H-2"]

    @pytest.mark.anyio
    async def test_a_post_on_a_new_connection_is_never_sent_twice(self, tmp_path: Path) -> None:
        with anyio.fail_after(20):
            async with ScriptedPeer(tmp_path, [Script("read, then closed", ())]) as peer:
                poster = poster_for(peer)
                try:
                    result, detail = await post(poster, 1)
                finally:
                    await poster.aclose()
        assert result == "retry"
        assert detail == (
            f"{peer.url}: connection lost: the server closed the connection before any answer"
        )
        assert peer.keys == ["H-1"]

    @pytest.mark.anyio
    async def test_chunk_extensions_and_trailers_are_read_and_the_connection_kept(
        self, tmp_path: Path
    ) -> None:
        trailer = Script(
            "chunked, extension, trailer",
            (
                b"HTTP/1.1 201 Created\r\nTransfer-Encoding: chunked\r\n\r\n"
                b"2;ext=1\r\n{}\r\n0\r\nX-Trailer: 1\r\n\r\n",
            ),
            close=False,
        )
        with anyio.fail_after(20):
            async with ScriptedPeer(tmp_path, [trailer]) as peer:
                poster = poster_for(peer)
                try:
                    results = [await post(poster, 1), await post(poster, 2)]
                finally:
                    await poster.aclose()
        assert results == [("delivered", ""), ("delivered", "")]
        assert peer.connections == 1

    @pytest.mark.anyio
    async def test_interim_answers_are_skipped(self, tmp_path: Path) -> None:
        interim = Script(
            "100 then 201",
            (b"HTTP/1.1 100 Continue\r\n\r\n", OK_KEPT.parts[0]),
            close=False,
        )
        with anyio.fail_after(20):
            async with ScriptedPeer(tmp_path, [interim]) as peer:
                poster = poster_for(peer)
                try:
                    results = [await post(poster, 1), await post(poster, 2)]
                finally:
                    await poster.aclose()
        assert results == [("delivered", ""), ("delivered", "")]
        assert peer.connections == 1


class TestHostileAnswers:
    """Whatever the battery sends back, the POST ends by the deadline with a clear retry."""

    @pytest.mark.anyio
    async def test_each_hostile_answer_is_a_retry_saying_why_and_then_delivery(
        self, tmp_path: Path
    ) -> None:
        with anyio.fail_after(30):
            async with ScriptedPeer(tmp_path, list(HOSTILE)) as peer:
                poster = poster_for(peer, timeout_s=1.0)
                try:
                    results = [await post(poster, n) for n in range(len(HOSTILE) + 1)]
                finally:
                    await poster.aclose()
        url = peer.url
        assert results == [
            ("retry", f"{url}: unreadable answer: not an HTTP/1.1 answer: b'SSH-2.0-OpenSSH_9.6'"),
            (
                "retry",
                f"{url}: unreadable answer: the answer's head longer than {MAX_HEAD_BYTES} bytes",
            ),
            (
                "retry",
                f"{url}: unreadable answer: more than {MAX_HEADERS} header lines in the answer",
            ),
            ("retry", f"{url}: connection lost: the server closed the connection mid-answer"),
            ("retry", f"{url}: unreadable answer: bad chunk size in the answer: b'ZZ\\r\\n'"),
            ("retry", f"{url}: no answer within 1.0 s"),
            ("delivered", ""),
        ]
        assert peer.played == [s.name for s in HOSTILE]

    @pytest.mark.anyio
    async def test_a_huge_refusal_is_read_only_up_to_the_bound(self, tmp_path: Path) -> None:
        huge = Script(
            "huge 422",
            (b"HTTP/1.1 422 Unprocessable\r\nContent-Length: 10000000\r\n\r\n" + b"r" * 4096,),
            close=False,
        )
        with anyio.fail_after(20):
            async with ScriptedPeer(tmp_path, [huge]) as peer:
                poster = poster_for(peer)
                try:
                    refused = await post(poster, 1)
                    delivered = await post(poster, 2)
                finally:
                    await poster.aclose()
        assert refused == ("refused", "HTTP 422: " + "r" * MAX_REASON_BYTES)
        assert delivered == ("delivered", "")
        assert peer.connections == 2  # the rest of the 10 MB was never read: dropped

    @pytest.mark.anyio
    async def test_an_answer_without_a_length_is_read_to_the_close(self, tmp_path: Path) -> None:
        old_server = Script("HTTP/1.0, no length", (b"HTTP/1.0 422 Nope\r\n\r\nbad ", b"document"))
        with anyio.fail_after(20):
            async with ScriptedPeer(tmp_path, [old_server]) as peer:
                poster = poster_for(peer)
                try:
                    results = [await post(poster, 1), await post(poster, 2)]
                finally:
                    await poster.aclose()
        assert results == [("refused", "HTTP 422: bad document"), ("delivered", "")]
        assert peer.connections == 2

    @pytest.mark.anyio
    async def test_a_key_no_header_can_carry_is_refused_unsent(self, tmp_path: Path) -> None:
        bad = SAMPLE.model_copy(update={"event_id": "H-1\r\nX-Evil: 1"})
        with anyio.fail_after(20):
            async with ScriptedPeer(tmp_path) as peer:
                poster = poster_for(peer)
                try:
                    (outcome,) = await poster.post_all([bad], lambda _: b"{}")
                finally:
                    await poster.aclose()
        assert outcome.result == "refused"
        assert outcome.detail.startswith("header Idempotency-Key cannot be sent")
        assert peer.keys == []


def test_the_request_target_is_percent_encoded_where_it_must_be() -> None:
    origin = Http1Origin(
        "https://battery.example:8443/gute 2/ü?site=Nord 1&x=%20",
        ssl.create_default_context(),
        max_connections=1,
    )
    assert origin.target == "/gute%202/%C3%BC?site=Nord%201&x=%20"


@pytest.mark.anyio
@pytest.mark.parametrize("size", [b"0x0", b"+0", b"-0", b"0_0", b"-5", b""])
async def test_a_chunk_size_not_in_hex_digits_is_unreadable(tmp_path: Path, size: bytes) -> None:
    # int(text, 16) would take each of these (but the empty one): "0x0" as the last chunk.
    lying = Script(
        "chunk size not hex",
        (b"HTTP/1.1 201 Created\r\nTransfer-Encoding: chunked\r\n\r\n" + size + b"\r\n\r\n",),
        close=False,
    )
    with anyio.fail_after(20):
        async with ScriptedPeer(tmp_path, [lying]) as peer:
            poster = poster_for(peer)
            try:
                result, detail = await post(poster, 1)
            finally:
                await poster.aclose()
    assert result == "retry"
    assert "bad chunk size in the answer" in detail
