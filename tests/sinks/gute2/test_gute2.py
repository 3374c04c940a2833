"""The gute2 sink against a real HTTPS battery (GutePeer) on loopback, driven by SinkRunner."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import anyio
import pytest
import trustme
from gute_peer import GutePeer
from pydantic import ValidationError

from gateway.c2.sinkrunner import SinkRunner
from gateway.config import SinkEntry
from gateway.contract import check_sink, sample_events
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import EventKind, Handoff
from gateway.ops.instruments import Instruments
from gateway.testing import eventually
from gateway.transports.https import describe_https_error, https_client
from gateway.transports.tls import TlsFiles
from sinks.gute2.codec import SCHEMA_ID
from sinks.gute2.sink import GuteSink, GuteSinkConfig

SAMPLE = sample_events(frozenset({EventKind.HANDOFF}))[0]
assert isinstance(SAMPLE, Handoff)


def handoff(n: int) -> Handoff:
    key = f"H-{n}"
    return SAMPLE.model_copy(update={"event_id": key, "handoff_id": key})


def sink(options: dict[str, Any]) -> GuteSink:
    return GuteSink("gute", GuteSinkConfig.model_validate(options))


def runner_for(gute: GuteSink) -> SinkRunner:
    entry = SinkEntry(
        name="gute", type="gute2", send_timeout_s=5.0, retry_initial_s=0.01, retry_max_s=0.05
    )
    return SinkRunner(entry, gute, Instruments())


async def run_until(runner: SinkRunner, done: Any) -> None:
    async with anyio.create_task_group() as tg:
        await tg.start(runner.run)
        await eventually(done)
        runner.stop()
        await runner.wait_done()


class TestDelivery:
    """Through the real SinkRunner: delivered once each, retried when the battery is busy."""

    @pytest.mark.anyio
    async def test_handoffs_are_posted_with_their_idempotency_key(self, tmp_path: Path) -> None:
        with anyio.fail_after(20):
            async with GutePeer(tmp_path) as peer:
                runner = runner_for(sink(peer.sink_options()))
                for n in range(3):
                    runner.offer(handoff(n), 0.0)
                await run_until(runner, lambda: len(peer.accepted) == 3)
        assert set(peer.accepted) == {"H-0", "H-1", "H-2"}  # up to max_in_flight at once
        for request in peer.posts:
            assert request.headers["content-type"] == "application/json"
            assert request.headers["idempotency-key"] in peer.accepted
        document = peer.accepted["H-1"]
        assert document["schema"] == SCHEMA_ID
        assert document["operator_authorisation_required"] is True
        assert runner.dead_letters == type(runner.dead_letters)()

    @pytest.mark.anyio
    async def test_a_busy_battery_is_retried_and_records_each_handoff_once(
        self, tmp_path: Path
    ) -> None:
        with anyio.fail_after(20):
            async with GutePeer(tmp_path, fail_first=3) as peer:
                runner = runner_for(sink(peer.sink_options(max_in_flight=1)))
                for n in range(2):
                    runner.offer(handoff(n), 0.0)
                await run_until(runner, lambda: len(peer.accepted) == 2)
        statuses = [r.status for r in peer.posts]
        assert statuses.count(503) == 3
        assert set(peer.accepted) == {"H-0", "H-1"}
        # A batch retried after a partial success is answered 409 and still counted once.
        assert all(s in (201, 409, 503) for s in statuses)
        assert not runner.dead_letters

    @pytest.mark.anyio
    async def test_a_dropped_connection_is_transient(self, tmp_path: Path) -> None:
        async with GutePeer(tmp_path, drop_first=1) as peer:
            gute = sink(peer.sink_options())
            with anyio.fail_after(10):
                await gute.open()
                with pytest.raises(TransientSinkError, match=r"connection lost") as caught:
                    await gute.send([handoff(1)])
                await gute.send([handoff(1)])
                await gute.aclose()
        assert peer.url in str(caught.value)
        assert list(peer.accepted) == ["H-1"]

    @pytest.mark.anyio
    async def test_a_repeated_key_is_delivered_not_refused(self, tmp_path: Path) -> None:
        async with GutePeer(tmp_path) as peer:
            gute = sink(peer.sink_options())
            with anyio.fail_after(10):
                await gute.open()
                await gute.send([handoff(1)])
                await gute.send([handoff(1)])
                await gute.aclose()
        assert [r.status for r in peer.posts] == [201, 409]
        assert len(peer.accepted) == 1

    @pytest.mark.anyio
    async def test_a_refused_handoff_alone_is_dead_lettered(self, tmp_path: Path) -> None:
        with anyio.fail_after(20):
            async with GutePeer(tmp_path, refuse={"H-1": 422}) as peer:
                runner = runner_for(sink(peer.sink_options()))
                for n in range(3):
                    runner.offer(handoff(n), 0.0)
                await run_until(
                    runner, lambda: len(peer.accepted) == 2 and len(runner.dead_letters) == 1
                )
        assert set(peer.accepted) == {"H-0", "H-2"}
        event, reason = runner.dead_letters[0]
        assert event.event_id == "H-1"
        assert "HTTP 422" in reason
        assert "refused by the test" in reason

    @pytest.mark.anyio
    async def test_the_permanent_error_names_only_the_refused_events(self, tmp_path: Path) -> None:
        async with GutePeer(tmp_path, refuse={"H-2": 400}) as peer:
            gute = sink(peer.sink_options())
            with anyio.fail_after(10):
                await gute.open()
                with pytest.raises(PermanentSinkError) as caught:
                    await gute.send([handoff(1), handoff(2), handoff(3)])
                await gute.aclose()
        assert caught.value.event_ids == frozenset({"H-2"})
        assert set(peer.accepted) == {"H-1", "H-3"}


class TestTls:
    """Certificates are checked both ways, and a failure says which file is at fault."""

    @pytest.mark.anyio
    async def test_a_foreign_client_certificate_is_refused_and_named(self, tmp_path: Path) -> None:
        stranger = trustme.CA().issue_cert("someone-else")
        stranger_file = tmp_path / "stranger.pem"
        stranger.private_key_and_cert_chain_pem.write_to_path(str(stranger_file))
        async with GutePeer(tmp_path) as peer:
            options = {**peer.sink_options(), "cert_file": str(stranger_file), "key_file": None}
            gute = sink(options)
            with anyio.fail_after(10):
                await gute.open()
                with pytest.raises(TransientSinkError) as caught:
                    await gute.send([handoff(1)])
                await gute.aclose()
        assert f"refused the client certificate {stranger_file}" in str(caught.value)
        assert peer.accepted == {}
        assert peer.posts == []
        assert peer.handshake_failures

    @pytest.mark.anyio
    async def test_no_client_certificate_is_refused_at_the_handshake(self, tmp_path: Path) -> None:
        async with GutePeer(tmp_path) as peer:
            files = TlsFiles(peer.ca_file)
            client = await https_client(
                files,
                connect_timeout_s=5,
                read_timeout_s=5,
                write_timeout_s=5,
                pool_timeout_s=5,
            )
            with anyio.fail_after(10):
                async with client:
                    with pytest.raises(Exception) as caught:  # noqa: PT011 - described below
                        await client.post(peer.url, content=b"{}")
        assert describe_https_error(caught.value, peer.url, files) == (
            f"{peer.url}: the server requires a client certificate and none is configured"
        )
        assert peer.requests == []
        assert peer.handshake_failures == ["PEER_DID_NOT_RETURN_A_CERTIFICATE"]

    @pytest.mark.anyio
    async def test_a_server_from_another_ca_is_refused_naming_the_ca_file(
        self, tmp_path: Path
    ) -> None:
        other_ca = tmp_path / "other-ca.pem"
        trustme.CA().cert_pem.write_to_path(str(other_ca))
        async with GutePeer(tmp_path) as peer:
            gute = sink({**peer.sink_options(), "ca_file": str(other_ca)})
            with anyio.fail_after(10):
                await gute.open()
                with pytest.raises(TransientSinkError) as caught:
                    await gute.send([handoff(1)])
                await gute.aclose()
        assert f"not trusted by the pinned CA {other_ca}" in str(caught.value)
        assert peer.posts == []

    @pytest.mark.anyio
    async def test_a_certificate_for_another_name_is_refused_naming_the_host(
        self, tmp_path: Path
    ) -> None:
        async with GutePeer(tmp_path, server_name="battery.example") as peer:
            gute = sink(peer.sink_options())
            with anyio.fail_after(10):
                await gute.open()
                refused = r"not valid for hostname '127\.0\.0\.1'"
                with pytest.raises(TransientSinkError, match=refused):
                    await gute.send([handoff(1)])
                await gute.aclose()


class TestConfig:
    """Mistakes are config errors that name the option or the file."""

    def test_plain_http_is_refused_naming_the_option(self, tmp_path: Path) -> None:
        with pytest.raises(ValidationError, match=r"url\n.*expected https://") as caught:
            GuteSinkConfig.model_validate(
                {"url": "http://battery:8443/h", "ca_file": "ca.pem", "cert_file": "c.pem"}
            )
        assert caught.value.errors()[0]["loc"] == ("url",)

    @pytest.mark.parametrize(
        "files",
        [
            {},
            {"cert_file": "c.pem", "pkcs12_file": "c.p12"},
            {"pkcs12_file": "c.p12", "key_file": "k.pem"},
        ],
    )
    def test_exactly_one_client_certificate(self, files: dict[str, str]) -> None:
        with pytest.raises(ValidationError, match=r"exactly one of|key_file goes with"):
            GuteSinkConfig.model_validate(
                {"url": "https://battery/h", "ca_file": "ca.pem", **files}
            )

    def test_on_the_node_a_missing_file_is_named(self, tmp_path: Path) -> None:
        peer = GutePeer(tmp_path)
        missing = tmp_path / "nope.pem"
        options = {**peer.sink_options(), "cert_file": str(missing)}
        GuteSinkConfig.model_validate(options)  # off the node, paths are not read
        with pytest.raises(ValidationError, match=str(missing)):
            GuteSinkConfig.model_validate(options, context={"environment": True})
        GuteSinkConfig.model_validate(peer.sink_options(), context={"environment": True})

    @pytest.mark.anyio
    async def test_open_names_an_unreadable_file(self, tmp_path: Path) -> None:
        peer = GutePeer(tmp_path)
        missing = tmp_path / "gone-ca.pem"
        gute = sink({**peer.sink_options(), "ca_file": str(missing)})
        with pytest.raises(TransientSinkError, match=str(missing)):
            await gute.open()
        await gute.aclose()


def test_keeps_the_sink_contract(tmp_path: Path) -> None:
    with GutePeer(tmp_path).in_thread() as peer:
        check_sink(GuteSink, peer.sink_options())
        assert list(peer.accepted) == ["c-ho"]
