"""The slb sink against a real HTTPS SLB (SlbPeer) on loopback, alone and driven by SinkRunner."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import anyio
import pytest
import trustme
from pydantic import ValidationError
from slb_peer import SlbPeer
from structlog.testing import capture_logs

from gateway.c2.sinkrunner import SinkRunner
from gateway.config import SinkEntry
from gateway.contract import check_sink, sample_events
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import Detection, EventKind, Track
from gateway.ops.instruments import Instruments
from gateway.testing import eventually
from sinks.slb.jc3iedm import SCHEMA_ID
from sinks.slb.sink import SlbSink, SlbSinkConfig

DETECTION, TRACK = sample_events(frozenset({EventKind.DETECTION, EventKind.TRACK}))
assert isinstance(DETECTION, Detection)
assert isinstance(TRACK, Track)


def detection(n: int) -> Detection:
    return DETECTION.model_copy(update={"event_id": f"D-{n}"})


def track(n: int) -> Track:
    return TRACK.model_copy(update={"event_id": f"T-{n}", "track_id": f"TRK-{n % 2}"})


def sink(options: dict[str, Any]) -> SlbSink:
    return SlbSink("slb", SlbSinkConfig.model_validate(options))


def runner_for(slb: SlbSink) -> SinkRunner:
    entry = SinkEntry(
        name="slb", type="slb", send_timeout_s=5.0, retry_initial_s=0.01, retry_max_s=0.05
    )
    return SinkRunner(entry, slb, Instruments())


async def run_until(runner: SinkRunner, done: Any) -> None:
    async with anyio.create_task_group() as tg:
        await tg.start(runner.run)
        await eventually(done)
        runner.stop()
        await runner.wait_done()


class TestDelivery:
    """Through the real SinkRunner: each report accepted once, whatever was retried."""

    @pytest.mark.anyio
    async def test_detections_and_tracks_are_posted_with_their_idempotency_key(
        self, tmp_path: Path
    ) -> None:
        with anyio.fail_after(20):
            async with SlbPeer(tmp_path) as peer:
                runner = runner_for(sink(peer.sink_options()))
                for n in range(3):
                    runner.offer(detection(n), 0.0)
                    runner.offer(track(n), 0.0)
                await run_until(runner, lambda: len(peer.accepted) == 6)
        assert set(peer.accepted) == {"D-0", "D-1", "D-2", "T-0", "T-1", "T-2"}
        for request in peer.posts:
            assert request.path == "/slb/api/object-items"
            assert request.headers["content-type"] == "application/json"
            assert request.headers["idempotency-key"] in peer.accepted
        assert peer.accepted["T-1"]["schema"] == SCHEMA_ID
        assert peer.accepted["T-1"]["object_item"]["obj_item_id"] == "fg:track:TRK-1"
        assert peer.accepted["D-2"]["reporting_data"]["cat_code"] == "REP"
        assert peer.duplicates == 0
        assert not runner.dead_letters

    @pytest.mark.anyio
    async def test_a_busy_slb_is_retried_and_records_each_report_once(self, tmp_path: Path) -> None:
        with anyio.fail_after(20):
            async with SlbPeer(tmp_path, fail_first=3) as peer:
                runner = runner_for(sink(peer.sink_options(max_in_flight=1)))
                for n in range(2):
                    runner.offer(detection(n), 0.0)
                await run_until(runner, lambda: len(peer.accepted) == 2)
        statuses = [r.status for r in peer.posts]
        assert statuses.count(503) == 3
        assert set(statuses) <= {201, 409, 503}  # a retried batch's delivered half is 409
        assert set(peer.accepted) == {"D-0", "D-1"}
        assert not runner.dead_letters

    @pytest.mark.anyio
    async def test_409_is_delivered_not_refused(self, tmp_path: Path) -> None:
        async with SlbPeer(tmp_path) as peer:
            slb = sink(peer.sink_options())
            with anyio.fail_after(10):
                await slb.open()
                await slb.send([detection(1)])
                await slb.send([detection(1)])  # raises nothing: already delivered
                await slb.aclose()
        assert [r.status for r in peer.posts] == [201, 409]
        assert peer.duplicates == 1
        assert list(peer.accepted) == ["D-1"]

    @pytest.mark.anyio
    async def test_a_refused_report_alone_is_dead_lettered(self, tmp_path: Path) -> None:
        with anyio.fail_after(20):
            async with SlbPeer(tmp_path, refuse={"D-1": 422}) as peer:
                runner = runner_for(sink(peer.sink_options()))
                for n in range(3):
                    runner.offer(detection(n), 0.0)
                await run_until(
                    runner, lambda: len(peer.accepted) == 2 and len(runner.dead_letters) == 1
                )
        assert set(peer.accepted) == {"D-0", "D-2"}
        event, reason = runner.dead_letters[0]
        assert event.event_id == "D-1"
        assert "HTTP 422" in reason
        assert "refused by the test" in reason

    @pytest.mark.anyio
    async def test_the_permanent_error_names_only_the_refused_events(self, tmp_path: Path) -> None:
        async with SlbPeer(tmp_path, refuse={"T-2": 422}) as peer:
            slb = sink(peer.sink_options())
            with anyio.fail_after(10):
                await slb.open()
                with pytest.raises(PermanentSinkError) as caught:
                    await slb.send([track(1), track(2), detection(3)])
                await slb.aclose()
        assert caught.value.event_ids == frozenset({"T-2"})
        assert set(peer.accepted) == {"T-1", "D-3"}

    @pytest.mark.anyio
    async def test_a_refused_batch_is_one_log_line_and_a_bounded_reason(
        self, tmp_path: Path
    ) -> None:
        keys = {f"D-{n}": 422 for n in range(8)}
        async with SlbPeer(tmp_path, refuse=keys) as peer:
            slb = sink(peer.sink_options())
            with capture_logs() as logs, anyio.fail_after(10):
                with pytest.raises(PermanentSinkError, match=r"; and 3 more$") as caught:
                    await slb.send([detection(n) for n in range(8)])
                await slb.aclose()
        assert caught.value.event_ids == frozenset(keys)
        (line,) = [e for e in logs if e["event"] == "slb_items_refused"]
        assert line["count"] == 8
        assert len(line["event_ids"]) == 5

    @pytest.mark.anyio
    async def test_a_value_json_cannot_hold_is_refused_without_a_post(self, tmp_path: Path) -> None:
        broken = detection(9).model_copy(update={"sigma_h_m": math.inf})
        async with SlbPeer(tmp_path) as peer:
            slb = sink(peer.sink_options())
            with anyio.fail_after(10):
                with pytest.raises(PermanentSinkError, match="cannot encode") as caught:
                    await slb.send([broken, detection(1)])
                await slb.aclose()
        assert caught.value.event_ids == frozenset({"D-9"})
        assert list(peer.accepted) == ["D-1"]

    @pytest.mark.anyio
    async def test_the_config_narrows_the_kinds(self, tmp_path: Path) -> None:
        async with SlbPeer(tmp_path) as peer:
            slb = sink(peer.sink_options(kinds=["track"]))
            assert slb.kinds == frozenset({EventKind.TRACK})
            with anyio.fail_after(10):
                await slb.send([detection(1), track(1)])
                await slb.aclose()
        assert list(peer.accepted) == ["T-1"]


class TestClassification:
    """Every status SLB may answer is taken by the one table the HTTPS sinks share."""

    @pytest.mark.parametrize(
        ("status", "outcome"),
        [
            (400, "refused"),
            (404, "refused"),
            (410, "refused"),
            (422, "refused"),
            (401, "retry"),  # our certificate not enrolled yet: an operator fixes it
            (403, "retry"),
            (408, "retry"),
            (425, "retry"),
            (429, "retry"),
            (500, "retry"),
            (502, "retry"),
            (503, "retry"),
            (301, "retry"),  # never followed: the configured URL is wrong
        ],
    )
    @pytest.mark.anyio
    async def test_status(self, tmp_path: Path, status: int, outcome: str) -> None:
        async with SlbPeer(tmp_path, refuse={"D-1": status}) as peer:
            slb = sink(peer.sink_options())
            expected = PermanentSinkError if outcome == "refused" else TransientSinkError
            with anyio.fail_after(10):
                with pytest.raises(expected, match=f"HTTP {status}") as caught:
                    await slb.send([detection(1), detection(2)])
                await slb.aclose()
        assert list(peer.accepted) == ["D-2"]
        if isinstance(caught.value, PermanentSinkError):
            assert caught.value.event_ids == frozenset({"D-1"})
        else:
            assert f"{peer.base_url}/object-items" in str(caught.value)


class TestRetryAfter:
    """A 429's or 503's Retry-After is honoured, and bounded by max_retry_after_s."""

    @pytest.mark.anyio
    async def test_slb_is_not_contacted_until_the_wait_is_over(self, tmp_path: Path) -> None:
        async with SlbPeer(tmp_path, busy_first=1, retry_after="3600") as peer:
            slb = sink(peer.sink_options(max_retry_after_s=0.3))
            with anyio.fail_after(10):
                with pytest.raises(TransientSinkError, match=r"HTTP 429.*asked for 0\.3 s"):
                    await slb.send([detection(1)])
                with pytest.raises(TransientSinkError, match="holding back"):
                    await slb.send([detection(1)])
                assert len(peer.posts) == 1  # the second send did not reach SLB
                # The hold is bounded (0.3 s, not the hour asked for); then SLB is asked again.
                await anyio.sleep(0.35)
                await slb.send([detection(1)])
                await slb.aclose()
        assert [r.status for r in peer.posts] == [429, 201]
        assert list(peer.accepted) == ["D-1"]

    @pytest.mark.anyio
    async def test_a_503_without_retry_after_only_backs_off_in_the_runner(
        self, tmp_path: Path
    ) -> None:
        async with SlbPeer(tmp_path, fail_first=1) as peer:
            slb = sink(peer.sink_options())
            with anyio.fail_after(10):
                with pytest.raises(TransientSinkError, match="HTTP 503") as caught:
                    await slb.send([detection(1)])
                await slb.send([detection(1)])
                await slb.aclose()
        assert "Retry-After" not in str(caught.value)
        assert list(peer.accepted) == ["D-1"]


class TestUnreachable:
    """A lost connection or an SLB that is down is transient and names the URL."""

    @pytest.mark.anyio
    async def test_a_dropped_connection_is_transient(self, tmp_path: Path) -> None:
        async with SlbPeer(tmp_path, drop_first=1) as peer:
            slb = sink(peer.sink_options())
            with anyio.fail_after(10):
                with pytest.raises(TransientSinkError, match="connection lost") as caught:
                    await slb.send([detection(1)])
                await slb.send([detection(1)])
                await slb.aclose()
        assert peer.base_url in str(caught.value)
        assert list(peer.accepted) == ["D-1"]

    @pytest.mark.anyio
    async def test_slb_down_then_back(self, tmp_path: Path) -> None:
        async with SlbPeer(tmp_path) as peer:
            peer.down = True
            slb = sink(peer.sink_options())
            with anyio.fail_after(10):
                with pytest.raises(TransientSinkError, match=peer.base_url):
                    await slb.send([detection(1)])
                peer.down = False
                await slb.send([detection(1)])
                await slb.aclose()
        assert peer.refused_while_down >= 1
        assert list(peer.accepted) == ["D-1"]


class TestTls:
    """Certificates are checked both ways, and a failure says which file is at fault."""

    @pytest.mark.anyio
    async def test_a_foreign_client_certificate_is_refused_and_named(self, tmp_path: Path) -> None:
        stranger = trustme.CA().issue_cert("someone-else")
        stranger_file = tmp_path / "stranger.pem"
        stranger.private_key_and_cert_chain_pem.write_to_path(str(stranger_file))
        async with SlbPeer(tmp_path) as peer:
            slb = sink(peer.sink_options(cert_file=str(stranger_file), key_file=None))
            with anyio.fail_after(10):
                with pytest.raises(TransientSinkError) as caught:
                    await slb.send([detection(1)])
                await slb.aclose()
        assert f"refused the client certificate {stranger_file}" in str(caught.value)
        assert peer.posts == []
        assert peer.handshake_failures

    @pytest.mark.anyio
    async def test_a_server_from_another_ca_is_refused_naming_the_ca_file(
        self, tmp_path: Path
    ) -> None:
        other_ca = tmp_path / "other-ca.pem"
        trustme.CA().cert_pem.write_to_path(str(other_ca))
        async with SlbPeer(tmp_path) as peer:
            slb = sink(peer.sink_options(ca_file=str(other_ca)))
            with anyio.fail_after(10):
                with pytest.raises(TransientSinkError) as caught:
                    await slb.send([detection(1)])
                await slb.aclose()
        assert f"not trusted by the pinned CA {other_ca}" in str(caught.value)
        assert peer.posts == []

    @pytest.mark.anyio
    async def test_the_system_store_does_not_vouch_for_slb_unless_asked(
        self, tmp_path: Path
    ) -> None:
        """Trusting the system store as well still checks SLB's certificate."""
        other_ca = tmp_path / "other-ca.pem"
        trustme.CA().cert_pem.write_to_path(str(other_ca))
        async with SlbPeer(tmp_path) as peer:
            slb = sink(peer.sink_options(ca_file=str(other_ca), trust_system_store=True))
            with anyio.fail_after(10):
                with pytest.raises(TransientSinkError, match="or the system's CA store"):
                    await slb.send([detection(1)])
                await slb.aclose()
        assert peer.posts == []


class TestConfig:
    """Mistakes are config errors that name the option or the file."""

    @pytest.mark.parametrize(
        ("url", "problem"),
        [
            ("http://slb:8443/api", "expected https://"),
            ("https://user:pw@slb/api", "no credentials"),
            ("https://slb/api?x=1", "no query"),
            ("https://slb/api#top", "fragment"),
            ("https://slb:99999/api", "expected https://"),
        ],
    )
    def test_the_base_url_must_be_plain_https(self, url: str, problem: str) -> None:
        with pytest.raises(ValidationError, match=problem) as caught:
            SlbSinkConfig.model_validate(
                {"base_url": url, "ca_file": "ca.pem", "cert_file": "c.pem"}
            )
        assert caught.value.errors()[0]["loc"] == ("base_url",)

    def test_a_trailing_slash_is_dropped(self) -> None:
        config = SlbSinkConfig.model_validate(
            {"base_url": "https://slb:8443/api/", "ca_file": "ca.pem", "cert_file": "c.pem"}
        )
        assert config.url("/object-items") == "https://slb:8443/api/object-items"

    @pytest.mark.parametrize(
        "files",
        [
            {},
            {"cert_file": "c.pem", "pkcs12_file": "c.p12"},
            {"pkcs12_file": "c.p12", "key_file": "k"},
        ],
    )
    def test_exactly_one_client_certificate(self, files: dict[str, str]) -> None:
        with pytest.raises(ValidationError, match=r"exactly one of|key_file goes with"):
            SlbSinkConfig.model_validate({"base_url": "https://slb", "ca_file": "ca.pem", **files})

    def test_only_detections_and_tracks(self) -> None:
        base = {"base_url": "https://slb", "ca_file": "ca.pem", "cert_file": "c.pem"}
        with pytest.raises(ValidationError, match="kinds"):
            SlbSinkConfig.model_validate({**base, "kinds": ["handoff"]})
        with pytest.raises(ValidationError, match="kinds"):
            SlbSinkConfig.model_validate({**base, "kinds": []})

    def test_on_the_node_a_missing_file_is_named(self, tmp_path: Path) -> None:
        peer = SlbPeer(tmp_path)
        missing = tmp_path / "nope.pem"
        options = {**peer.sink_options(), "cert_file": str(missing)}
        SlbSinkConfig.model_validate(options)  # off the node, paths are not read
        with pytest.raises(ValidationError, match=str(missing)):
            SlbSinkConfig.model_validate(options, context={"environment": True})
        SlbSinkConfig.model_validate(peer.sink_options(), context={"environment": True})

    @pytest.mark.anyio
    async def test_open_names_an_unreadable_file(self, tmp_path: Path) -> None:
        peer = SlbPeer(tmp_path)
        missing = tmp_path / "gone-ca.pem"
        slb = sink(peer.sink_options(ca_file=str(missing)))
        with pytest.raises(TransientSinkError, match=str(missing)):
            await slb.open()
        await slb.aclose()


def test_keeps_the_sink_contract(tmp_path: Path) -> None:
    with SlbPeer(tmp_path).in_thread() as peer:
        check_sink(SlbSink, peer.sink_options())
        assert set(peer.accepted) == {"c-det", "c-trk"}
