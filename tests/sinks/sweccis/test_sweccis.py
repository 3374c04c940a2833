"""The sweccis sink against a real SWECCIS server (SweccisPeer: TLS, client certificates,
length frames, the XSD) on loopback, alone and driven by the SinkRunner."""

from __future__ import annotations

import struct
from datetime import timedelta
from pathlib import Path
from typing import Any

import anyio
import pytest
import trustme
from pydantic import ValidationError
from structlog.testing import capture_logs
from sweccis_peer import NS, SweccisPeer

from gateway.c2.sinkrunner import SinkRunner
from gateway.config import SinkEntry
from gateway.contract import check_sink, sample_events
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import Detection, EventKind, Telemetry, Track
from gateway.ops.instruments import Instruments
from gateway.testing import eventually
from sinks.sweccis.sink import SweccisSink, SweccisSinkConfig

SAMPLES = {e.kind: e for e in sample_events(frozenset(EventKind))}
DETECTION = SAMPLES[EventKind.DETECTION]
TRACK = SAMPLES[EventKind.TRACK]
TELEMETRY = SAMPLES[EventKind.TELEMETRY]
assert isinstance(DETECTION, Detection)
assert isinstance(TRACK, Track)
assert isinstance(TELEMETRY, Telemetry)


def detection(n: int) -> Detection:
    return DETECTION.model_copy(update={"event_id": f"D-{n}"})


def telemetry(n: int, seconds: float, airframe: str = "F26E-001") -> Telemetry:
    return TELEMETRY.model_copy(
        update={
            "event_id": f"{airframe}-tel-{n}",
            "airframe": airframe,
            "time": TELEMETRY.time + timedelta(seconds=seconds),
        }
    )


def sink(options: dict[str, Any]) -> SweccisSink:
    return SweccisSink("sweccis", SweccisSinkConfig.model_validate(options))


def runner_for(sweccis: SweccisSink) -> SinkRunner:
    entry = SinkEntry(
        name="sweccis", type="sweccis", send_timeout_s=5.0, retry_initial_s=0.01, retry_max_s=0.05
    )
    return SinkRunner(entry, sweccis, Instruments())


async def run_until(runner: SinkRunner, done: Any) -> None:
    async with anyio.create_task_group() as tg:
        await tg.start(runner.run)
        await eventually(done)
        runner.stop()
        await runner.wait_done()


class TestDelivery:
    """What the server gets: XSD-valid documents of the registered FAS, each acknowledged."""

    @pytest.mark.anyio
    async def test_detections_tracks_and_telemetry_reach_their_fas(self, tmp_path: Path) -> None:
        async with SweccisPeer(tmp_path) as peer:
            sweccis = sink(peer.link_options(client_id="node-7"))
            with anyio.fail_after(10):
                await sweccis.open()
                await sweccis.send([DETECTION, TRACK, TELEMETRY])
                await sweccis.aclose()
        assert peer.registrations == [("node-7", ["Intel", "Logistics", "Operations"], [])]
        assert peer.invalid == []
        assert list(peer.accepted) == ["c-det", "c-trk", "c-tel/logistics", "c-tel/operations"]
        assert [r.status for r in peer.documents[1:]] == ["accepted"] * 4
        (state,) = peer.of("Operations")
        assert state.findtext(f"{NS}AirframeState/{NS}Airframe") == "F26E-001"
        assert sweccis.counts["accepted"] == 4

    @pytest.mark.anyio
    async def test_narrowed_kinds_register_only_their_fas(self, tmp_path: Path) -> None:
        async with SweccisPeer(tmp_path) as peer:
            sweccis = sink(peer.link_options(kinds=["track"]))
            with anyio.fail_after(10):
                await sweccis.open()
                await sweccis.send([TRACK])
                await sweccis.aclose()
        assert sweccis.kinds == frozenset({EventKind.TRACK})
        assert peer.registrations[0][1] == ["Intel"]
        assert list(peer.accepted) == ["c-trk"]

    @pytest.mark.anyio
    async def test_telemetry_documents_keep_to_their_rates_per_airframe(
        self, tmp_path: Path
    ) -> None:
        """Ten reports 0.25 s apart (by their own time) from two airframes: Operations at
        1 Hz and Logistics at 0.5 Hz each; the spacing survives separate batches."""
        async with SweccisPeer(tmp_path) as peer:
            sweccis = sink(peer.link_options(logistics_max_rate_hz=0.5))
            with anyio.fail_after(10):
                await sweccis.open()
                for n in range(10):
                    await sweccis.send([telemetry(n, n * 0.25), telemetry(n, n * 0.25, "B")])
                await sweccis.aclose()
        operations = [d for d in peer.accepted if d.endswith("/operations")]
        logistics = [d for d in peer.accepted if d.endswith("/logistics")]
        assert operations == [
            f"{a}-tel-{n}/operations" for n in (0, 4, 8) for a in ("F26E-001", "B")
        ]
        assert logistics == [f"{a}-tel-{n}/logistics" for n in (0, 8) for a in ("F26E-001", "B")]
        assert sweccis.counts["skipped"] == 2 * (7 + 8)

    @pytest.mark.anyio
    async def test_a_repeated_event_is_delivered_not_refused(self, tmp_path: Path) -> None:
        async with SweccisPeer(tmp_path) as peer:
            sweccis = sink(peer.link_options())
            with anyio.fail_after(10):
                await sweccis.open()
                await sweccis.send([detection(1), detection(1)])  # once on the wire
                await sweccis.send([detection(1)])
                await sweccis.aclose()
        assert [(r.doc_id, r.status) for r in peer.documents[1:]] == [
            ("D-1", "accepted"),
            ("D-1", "duplicate"),
        ]

    @pytest.mark.anyio
    async def test_lost_acks_time_out_and_the_retry_is_answered_duplicate(
        self, tmp_path: Path
    ) -> None:
        with anyio.fail_after(20):
            async with SweccisPeer(tmp_path, drop_acks=1) as peer:
                runner = runner_for(sink(peer.link_options(timeout_s=0.3)))
                for n in range(3):
                    runner.offer(detection(n), 0.0)
                await run_until(runner, lambda: runner.status()["sent"] == 3)
        statuses = [(r.doc_id, r.status) for r in peer.documents if r.root == "Intel"]
        assert statuses[0] == ("D-0", None)  # recorded, never acknowledged
        assert ("D-0", "duplicate") in statuses
        assert set(peer.accepted) == {"D-0", "D-1", "D-2"}
        assert len(peer.registrations) == 2  # the link was dropped after the timeout
        assert not runner.dead_letters

    @pytest.mark.anyio
    async def test_a_server_that_hung_up_meanwhile_is_reconnected_at_once(
        self, tmp_path: Path
    ) -> None:
        async with SweccisPeer(tmp_path) as peer:
            sweccis = sink(peer.link_options())
            with anyio.fail_after(10):
                await sweccis.open()
                await sweccis.send([detection(1)])
                await peer.close_all()
                await sweccis.send([detection(2)])  # no error: one fresh connection
                await sweccis.aclose()
        assert list(peer.accepted) == ["D-1", "D-2"]
        assert peer.connection_count == 2


class TestRefusals:
    """Rejected documents are permanent for their events alone; failures are transient."""

    @pytest.mark.anyio
    async def test_the_permanent_error_names_only_the_rejected_events(self, tmp_path: Path) -> None:
        async with SweccisPeer(tmp_path, reject={"D-2": "unknown sensor"}) as peer:
            sweccis = sink(peer.link_options())
            with anyio.fail_after(10):
                await sweccis.open()
                with pytest.raises(PermanentSinkError) as caught:
                    await sweccis.send([detection(1), detection(2), detection(3)])
                await sweccis.aclose()
        assert caught.value.event_ids == frozenset({"D-2"})
        assert "Intel D-2 rejected: unknown sensor" in str(caught.value)
        assert list(peer.accepted) == ["D-1", "D-3"]

    @pytest.mark.anyio
    async def test_through_the_runner_only_the_rejected_event_is_dead_lettered(
        self, tmp_path: Path
    ) -> None:
        with anyio.fail_after(20):
            async with SweccisPeer(tmp_path, reject={"D-1": "stale"}) as peer:
                runner = runner_for(sink(peer.link_options()))
                for n in range(3):
                    runner.offer(detection(n), 0.0)
                await run_until(runner, lambda: len(runner.dead_letters) == 1)
        assert set(peer.accepted) == {"D-0", "D-2"}
        event, reason = runner.dead_letters[0]
        assert event.event_id == "D-1"
        assert "stale" in reason

    @pytest.mark.anyio
    async def test_an_event_the_schema_cannot_hold_is_refused_alone(self, tmp_path: Path) -> None:
        broken = detection(9).model_copy(update={"object_class": "x" * 65})
        async with SweccisPeer(tmp_path) as peer:
            sweccis = sink(peer.link_options())
            with anyio.fail_after(10), capture_logs() as logs:
                await sweccis.open()
                with pytest.raises(PermanentSinkError, match="Class: 65 characters") as caught:
                    await sweccis.send([detection(1), broken])
                await sweccis.aclose()
        assert caught.value.event_ids == frozenset({"D-9"})
        assert list(peer.accepted) == ["D-1"]
        assert [e["event"] for e in logs if e["log_level"] == "warning"] == [
            "sweccis_event_refused"
        ]

    @pytest.mark.anyio
    async def test_a_document_over_the_frame_bound_is_refused_not_retried(
        self, tmp_path: Path
    ) -> None:
        crowded = TRACK.model_copy(update={"airframes": tuple(f"{n:0>100}" for n in range(60))})
        async with SweccisPeer(tmp_path) as peer:
            sweccis = sink(peer.link_options(max_frame_bytes=4096))
            with anyio.fail_after(10):
                await sweccis.open()
                with pytest.raises(PermanentSinkError, match="more than max_frame_bytes 4096"):
                    await sweccis.send([crowded, detection(1)])
                await sweccis.aclose()
        assert list(peer.accepted) == ["D-1"]

    @pytest.mark.anyio
    async def test_a_server_that_is_down_is_transient_naming_the_endpoint(
        self, tmp_path: Path
    ) -> None:
        async with SweccisPeer(tmp_path) as peer:
            peer.is_down = True
            sweccis = sink(peer.link_options())
            with anyio.fail_after(10):
                with pytest.raises(TransientSinkError, match=peer.uri):
                    await sweccis.send([detection(1)])
                peer.is_down = False
                await sweccis.send([detection(1)])
                await sweccis.aclose()
        assert list(peer.accepted) == ["D-1"]

    @pytest.mark.anyio
    @pytest.mark.parametrize(
        ("knobs", "reason"),
        [
            ({"refuse_registration": "client not enrolled"}, "refused: client not enrolled"),
            ({"withhold": frozenset({"Operations"})}, "did not register Operations"),
        ],
    )
    async def test_a_registration_short_of_the_fas_is_transient(
        self, tmp_path: Path, knobs: dict[str, Any], reason: str
    ) -> None:
        async with SweccisPeer(tmp_path, **knobs) as peer:
            sweccis = sink(peer.link_options())
            with anyio.fail_after(10), pytest.raises(TransientSinkError, match=reason):
                await sweccis.open()
            await sweccis.aclose()
        assert peer.accepted == {}

    @pytest.mark.anyio
    async def test_garbage_from_the_server_is_counted_and_skipped(self, tmp_path: Path) -> None:
        garbage = struct.pack(">I", 5) + b"\x00\xffjk!"
        async with SweccisPeer(tmp_path, noise=garbage) as peer:
            sweccis = sink(peer.link_options())
            with anyio.fail_after(10):
                await sweccis.open()
                await sweccis.send([detection(1), detection(2)])
                await sweccis.aclose()
        assert list(peer.accepted) == ["D-1", "D-2"]
        assert sweccis.counts["invalid"] == 2

    @pytest.mark.anyio
    async def test_an_oversize_frame_from_the_server_drops_the_link(self, tmp_path: Path) -> None:
        async with SweccisPeer(tmp_path, noise=struct.pack(">I", 1 << 30)) as peer:
            sweccis = sink(peer.link_options())
            with anyio.fail_after(10):
                await sweccis.open()
                with pytest.raises(TransientSinkError, match="exceeds the 65536-byte limit"):
                    await sweccis.send([detection(1)])
                peer.noise = None
                await sweccis.send([detection(1)])
                await sweccis.aclose()
        assert [r.status for r in peer.documents if r.root == "Intel"] == [
            "accepted",
            "duplicate",
        ]


class TestTls:
    """Certificates are checked both ways, and a failure says which file is at fault."""

    @pytest.mark.anyio
    async def test_a_foreign_client_certificate_is_refused_and_named(self, tmp_path: Path) -> None:
        stranger = trustme.CA().issue_cert("someone-else")
        stranger_file = tmp_path / "stranger.pem"
        stranger.private_key_and_cert_chain_pem.write_to_path(str(stranger_file))
        async with SweccisPeer(tmp_path) as peer:
            sweccis = sink(peer.link_options(cert_file=str(stranger_file), key_file=None))
            with anyio.fail_after(10), pytest.raises(TransientSinkError) as caught:
                await sweccis.open()
            await sweccis.aclose()
        assert f"refused the client certificate {stranger_file}" in str(caught.value)
        assert peer.handshake_failures
        assert peer.registrations == []

    @pytest.mark.anyio
    async def test_a_server_from_another_ca_is_refused_naming_the_ca_file(
        self, tmp_path: Path
    ) -> None:
        other_ca = tmp_path / "other-ca.pem"
        trustme.CA().cert_pem.write_to_path(str(other_ca))
        async with SweccisPeer(tmp_path) as peer:
            sweccis = sink(peer.link_options(ca_file=str(other_ca)))
            with anyio.fail_after(10), pytest.raises(TransientSinkError) as caught:
                await sweccis.open()
        assert f"not trusted by the pinned CA {other_ca}" in str(caught.value)

    @pytest.mark.anyio
    async def test_a_certificate_for_another_name_is_refused_naming_the_host(
        self, tmp_path: Path
    ) -> None:
        async with SweccisPeer(tmp_path, server_name="sweccis.example") as peer:
            sweccis = sink(peer.link_options())
            refused = r"not valid for hostname '127\.0\.0\.1'"
            with anyio.fail_after(10), pytest.raises(TransientSinkError, match=refused):
                await sweccis.open()
            sweccis = sink(peer.link_options(server_hostname="sweccis.example"))
            with anyio.fail_after(10):
                await sweccis.open()
                await sweccis.aclose()
        assert len(peer.registrations) == 1


class TestConfig:
    """Mistakes are config errors that name the option or the file."""

    @pytest.mark.parametrize(
        "uri",
        ["tcp://server:9443", "tls://server", "tls://user:pw@server:1", "tls://server:1/path"],
    )
    def test_only_a_tls_endpoint(self, uri: str) -> None:
        with pytest.raises(ValidationError) as caught:
            SweccisSinkConfig.model_validate({"uri": uri, "ca_file": "ca", "cert_file": "c"})
        assert caught.value.errors()[0]["loc"] == ("uri",)

    @pytest.mark.parametrize("files", [{}, {"cert_file": "c.pem", "pkcs12_file": "c.p12"}])
    def test_exactly_one_client_certificate(self, files: dict[str, str]) -> None:
        with pytest.raises(ValidationError, match="exactly one of"):
            SweccisSinkConfig.model_validate({"uri": "tls://s:1", "ca_file": "ca", **files})

    def test_kinds_without_a_fas_are_refused(self) -> None:
        with pytest.raises(ValidationError, match=r"not \['handoff'\]"):
            SweccisSinkConfig.model_validate(
                {"uri": "tls://s:1", "ca_file": "ca", "cert_file": "c", "kinds": ["handoff"]}
            )

    def test_on_the_node_a_missing_file_is_named(self, tmp_path: Path) -> None:
        good = SweccisPeer(tmp_path).link_options(uri="tls://127.0.0.1:9")  # not started
        missing = tmp_path / "nope.pem"
        options = {**good, "key_file": str(missing)}
        SweccisSinkConfig.model_validate(options)  # off the node, paths are not read
        with pytest.raises(ValidationError, match=str(missing)):
            SweccisSinkConfig.model_validate(options, context={"environment": True})
        SweccisSinkConfig.model_validate(good, context={"environment": True})


def test_keeps_the_sink_contract(tmp_path: Path) -> None:
    with SweccisPeer(tmp_path).in_thread() as peer:
        check_sink(SweccisSink, peer.link_options())
        assert list(peer.accepted) == ["c-tel/logistics", "c-tel/operations", "c-det", "c-trk"]
        assert peer.invalid == []
