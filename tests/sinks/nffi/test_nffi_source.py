"""The NFFI source: friendly tracks in over IP1 (TCP and TLS with client certificates) become
BlueForce events; everything else is counted, never raised, and peers are bounded."""

from __future__ import annotations

import contextlib
import ssl
from collections.abc import AsyncIterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import anyio
import pytest
import trustme
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from gateway.domain.peertext import Provenance
from gateway.events import BlueForce, Event, Position
from gateway.testing import fuzz_examples
from sinks.nffi.codec import NffiOptions, encode_message, tracks_of
from sinks.nffi.source import NffiSource, NffiSourceConfig

NOW = datetime(2026, 11, 22, 10, 16, 0, tzinfo=UTC)
OPTS = NffiOptions(system="JAS39-RELAY", country="SWE")


def report(
    uid: str = "39-7",
    at: datetime = NOW - timedelta(seconds=20),
    lat: float = 58.4,
    sidc: str | None = "SFAPMF---------",
    speed_mps: float = 250.0,
) -> bytes:
    """An NFFI document as a JAS 39 relay would send it (written by our encoder)."""
    friend = BlueForce(
        event_id="x",
        uid=uid,
        time=at,
        callsign="GRIPEN 7",
        position=Position(lat_deg=lat, lon_deg=15.6, alt_msl_m=3000.0),
        source="test",
        speed_mps=speed_mps,
        course_deg=45.0,
        sidc=sidc,
    )
    return encode_message(tracks_of([friend], OPTS))


def source(published: list[Event], **options: Any) -> NffiSource:
    values = {"uri": "tcp://127.0.0.1:0", "allow": ["127.0.0.0/8"], **options}
    config = NffiSourceConfig.model_validate(values)

    def publish(event: Event) -> bool:
        published.append(event)
        return True

    return NffiSource("nffi_in", config, publish, clock=lambda: NOW)


class TestConfig:
    def test_allow_list_is_required_and_tls_goes_with_tls(self) -> None:
        with pytest.raises(ValidationError, match="allow"):
            NffiSourceConfig.model_validate({"uri": "tcp://0.0.0.0:6000"})
        with pytest.raises(ValidationError, match="'tls' section"):
            NffiSourceConfig.model_validate({"uri": "tls://0.0.0.0:6000", "allow": ["0.0.0.0/0"]})
        with pytest.raises(ValidationError, match="tcp://HOST:PORT"):
            NffiSourceConfig.model_validate({"uri": "udp://0.0.0.0:6000", "allow": ["::/0"]})

    def test_a_missing_certificate_is_a_value_error_naming_it(self, tmp_path: Path) -> None:
        (tmp_path / "ca.pem").touch()
        config = NffiSourceConfig.model_validate(
            {
                "uri": "tls://127.0.0.1:0",
                "allow": ["127.0.0.1/32"],
                "tls": {
                    "cert_file": str(tmp_path / "s.pem"),
                    "client_ca_file": str(tmp_path / "ca.pem"),
                },
            }
        )
        with pytest.raises(ValueError, match=r"s\.pem: No such file"):
            NffiSource("n", config, lambda e: True)


class TestTracks:
    def test_a_friendly_track_becomes_blue_force_with_speed_in_mps(self) -> None:
        published: list[Event] = []
        nffi = source(published)
        assert nffi.handle(report())
        (event,) = published
        assert isinstance(event, BlueForce)
        assert event.uid == "SWE.JAS39-RELAY.39-7"
        assert (event.source, event.callsign, event.sidc) == ("nffi", "GRIPEN-7", "SFAPMF---------")
        assert event.speed_mps == pytest.approx(250.0)  # 900 km/h on the wire
        assert b"<speed>900</speed>" in report()
        assert (event.course_deg, event.position.alt_msl_m) == (45.0, 3000.0)
        assert nffi.counts == {"accepted": 1}
        # Plain TCP from an allow-listed address: an address check, not authentication.
        assert (event.source_name, event.provenance) == ("nffi_in", Provenance.ADDRESS_ONLY)

    def test_old_future_repeated_unfixed_and_hostile_tracks_are_counted_not_published(
        self,
    ) -> None:
        published: list[Event] = []
        nffi = source(published)
        nffi.handle(report(at=NOW - timedelta(seconds=30)))
        for document in [
            report(at=NOW - timedelta(seconds=30)),  # the same again
            report(at=NOW - timedelta(seconds=40)),  # older than the last
            report(uid="old", at=NOW - timedelta(hours=1)),
            report(uid="ahead", at=NOW + timedelta(minutes=5)),
            report(uid="hostile", sidc="SHAPMF---------"),
        ]:
            nffi.handle(document)
        no_fix = report(uid="nofix", lat=0.001).replace(b"<longitude>15.6", b"<longitude>0.001")
        nffi.handle(no_fix)
        nffi.handle(b"<event/>")
        nffi.handle(encode_message([]))
        assert len(published) == 1
        assert nffi.counts == {
            "accepted": 1,
            "duplicate": 1,
            "older": 1,
            "stale": 1,
            "future": 1,
            "not_friendly": 1,
            "no_fix": 1,
            "invalid": 1,
            "empty": 1,
        }
        assert nffi.problems == {"root": 1}

    @settings(max_examples=fuzz_examples(200), deadline=None)
    @given(st.binary(max_size=1500))
    def test_arbitrary_bytes_never_raise(self, data: bytes) -> None:
        published: list[Event] = []
        nffi = source(published, max_message_bytes=1024)
        assert nffi.handle(data) in (True, False)
        assert all(isinstance(e, BlueForce) for e in published)


@contextlib.asynccontextmanager
async def serving(nffi: NffiSource) -> AsyncIterator[int]:
    async with anyio.create_task_group() as tg:
        await tg.start(nffi.run)
        yield nffi.local_port
        tg.cancel_scope.cancel()


async def wait(condition: Any, what: str) -> None:
    """Until ``condition()`` holds (the source reads on its own task), at most 10 s."""
    for _ in range(1000):
        if condition():
            return
        await anyio.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.anyio
async def test_a_tcp_stream_of_documents_in_pieces_after_a_fragment() -> None:
    published: list[Event] = []
    nffi = source(published)
    async with serving(nffi) as port, await anyio.connect_tcp("127.0.0.1", port) as stream:
        data = b"</track>" + report("a") + report("b")
        for i in range(0, len(data), 100):
            await stream.send(data[i : i + 100])
        await wait(lambda: len(published) == 2, "two reports")
    assert {e.uid for e in published if isinstance(e, BlueForce)} == {
        "SWE.JAS39-RELAY.a",
        "SWE.JAS39-RELAY.b",
    }
    assert nffi.counts == {"accepted": 2, "fragment": 1}


@pytest.mark.anyio
async def test_a_peer_outside_the_allow_list_is_closed_unread() -> None:
    published: list[Event] = []
    nffi = source(published, allow=["10.0.0.0/8"])
    async with serving(nffi) as port, await anyio.connect_tcp("127.0.0.1", port) as stream:
        with contextlib.suppress(anyio.BrokenResourceError):
            await stream.send(report())
        with anyio.fail_after(10), pytest.raises((anyio.EndOfStream, anyio.BrokenResourceError)):
            await stream.receive()  # closed by the source, with nothing to say
    assert published == []
    assert nffi.counts == {"not_allowed": 1}


@pytest.mark.anyio
async def test_a_stream_without_a_document_end_is_closed_at_the_bound() -> None:
    published: list[Event] = []
    nffi = source(published, max_message_bytes=1024)
    async with serving(nffi) as port, await anyio.connect_tcp("127.0.0.1", port) as stream:
        with contextlib.suppress(anyio.BrokenResourceError):
            await stream.send(b"<NFFIMessage>" + b"<track>" * 400)
        with (
            anyio.fail_after(10),
            contextlib.suppress(anyio.BrokenResourceError, anyio.EndOfStream),
        ):
            await stream.receive()
        await wait(lambda: nffi.counts["oversize"] == 1, "oversize counted")
    assert published == []


@pytest.mark.anyio
async def test_tls_needs_a_client_certificate_from_the_ca(tmp_path: Path) -> None:
    ca = trustme.CA()
    ca.issue_cert("127.0.0.1").private_key_and_cert_chain_pem.write_to_path(
        str(tmp_path / "server.pem")
    )
    ca.cert_pem.write_to_path(str(tmp_path / "ca.pem"))
    tls = {"cert_file": str(tmp_path / "server.pem"), "client_ca_file": str(tmp_path / "ca.pem")}
    published: list[Event] = []
    nffi = source(published, uri="tls://127.0.0.1:0", tls=tls)
    client = ssl.create_default_context(ssl.Purpose.SERVER_AUTH)
    ca.configure_trust(client)
    async with serving(nffi) as port:
        # Without a certificate: the handshake fails (on the server, at least), nothing is read.
        with contextlib.suppress(
            ssl.SSLError, anyio.BrokenResourceError, anyio.EndOfStream, OSError
        ):
            async with await anyio.connect_tcp(
                "127.0.0.1", port, ssl_context=client, tls_standard_compatible=False
            ) as stream:
                await stream.send(report("stranger"))
                await stream.receive()
        await wait(lambda: nffi.counts["tls_failed"] == 1, "the refused handshake")
        ca.issue_cert("relay").configure_cert(client)
        async with await anyio.connect_tcp(
            "127.0.0.1", port, ssl_context=client, tls_standard_compatible=False
        ) as stream:
            await stream.send(report("member"))
            await wait(lambda: len(published) == 1, "the report over TLS")
    assert [e.uid for e in published if isinstance(e, BlueForce)] == ["SWE.JAS39-RELAY.member"]
    assert [e.provenance for e in published if isinstance(e, BlueForce)] == [
        Provenance.AUTHENTICATED
    ]


@pytest.mark.anyio
async def test_silent_peers_are_closed_and_evicted_for_new_ones() -> None:
    published: list[Event] = []
    nffi = source(published, idle_timeout_s=0.5, max_clients=1)
    async with serving(nffi) as port:
        silent = await anyio.connect_tcp("127.0.0.1", port)
        async with silent, await anyio.connect_tcp("127.0.0.1", port) as reporter:
            # The silent one never sent a document: the reporter takes its place.
            with (
                anyio.fail_after(10),
                pytest.raises((anyio.EndOfStream, anyio.BrokenResourceError)),
            ):
                await silent.receive()
            await reporter.send(report())
            await wait(lambda: len(published) == 1, "the reporter's track")
            with (
                anyio.fail_after(10),
                pytest.raises((anyio.EndOfStream, anyio.BrokenResourceError)),
            ):
                await reporter.receive()  # then silent for idle_timeout_s: closed
    assert nffi.counts["idle_closed"] == 1
    assert nffi.status()["connections"]["evicted"] == 1  # type: ignore[index]
