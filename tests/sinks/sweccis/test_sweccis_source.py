"""The sweccis order source against a real SWECCIS server (SweccisPeer) on loopback: orders
published and acknowledged only once held, bad ones rejected by name, and nothing the
server does ends the source."""

from __future__ import annotations

import struct
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import anyio
import pytest
from structlog.testing import capture_logs
from sweccis_peer import SweccisPeer, order_document

from gateway.events import Event, FiveLineOrder, OrderTask
from gateway.testing import eventually
from sinks.sweccis.source import SweccisSource, SweccisSourceConfig


class Intake:
    """What the source published; ``held`` decides what ``publish`` answers."""

    def __init__(self) -> None:
        self.events: list[Event] = []
        self.held = True

    def publish(self, event: Event) -> bool:
        self.events.append(event)
        return self.held


def source(peer: SweccisPeer, intake: Intake, **options: Any) -> SweccisSource:
    config = SweccisSourceConfig.model_validate(
        peer.link_options(reconnect_initial_s=0.05, reconnect_max_s=0.2, **options)
    )
    return SweccisSource("brigade", config, intake.publish)


@asynccontextmanager
async def running(sweccis: SweccisSource, peer: SweccisPeer) -> AsyncIterator[None]:
    """The source running, registered for Orders, for the block."""
    async with anyio.create_task_group() as tg:
        await tg.start(sweccis.run)
        await eventually(lambda: sweccis.state == "connected" and bool(peer.connections))
        yield
        tg.cancel_scope.cancel()


def acked(peer: SweccisPeer, count: int) -> Callable[[], bool]:
    return lambda: len(peer.order_acks) >= count


class TestOrders:
    """A valid order is published, then acknowledged; only once per document."""

    @pytest.mark.anyio
    async def test_an_order_is_published_then_acknowledged_accepted(self, tmp_path: Path) -> None:
        intake = Intake()
        async with SweccisPeer(tmp_path) as peer:
            sweccis = source(peer, intake, client_id="node-7")
            with anyio.fail_after(10):
                async with running(sweccis, peer):
                    area = [(65, 21), (65.1, 21), (65.1, 21.2)]
                    payload = order_document("doc-1", "ORD-1", task="recon_area", polygon=area)
                    await peer.push_order(payload)
                    await eventually(acked(peer, 1))
        assert peer.registrations == [("node-7", ["Orders"], ["Orders"])]
        (order,) = intake.events
        assert isinstance(order, FiveLineOrder)
        assert (order.event_id, order.source, order.task) == (
            "sweccis-order-ORD-1",
            "brigade",
            OrderTask.RECON_AREA,
        )
        assert peer.order_acks == [("doc-1", "accepted", None)]
        assert peer.outbox == {}
        assert sweccis.status()["counts"] == {"accepted": 1}

    @pytest.mark.anyio
    async def test_an_order_not_held_is_not_acknowledged_and_comes_again(
        self, tmp_path: Path
    ) -> None:
        """publish False: no ack, so the server still has it and sends it on the next
        connection; held then, it is acknowledged."""
        intake = Intake()
        intake.held = False
        async with SweccisPeer(tmp_path) as peer:
            sweccis = source(peer, intake)
            with anyio.fail_after(10):
                async with running(sweccis, peer):
                    await peer.push_order(order_document("doc-1", "ORD-1"))
                    await eventually(lambda: len(intake.events) == 1)
                    assert peer.order_acks == []
                    intake.held = True
                    await peer.close_all()
                    await eventually(acked(peer, 1))
        assert [e.event_id for e in intake.events] == ["sweccis-order-ORD-1"] * 2
        assert peer.order_acks == [("doc-1", "accepted", None)]
        assert sweccis.counts["not_held"] == 1
        assert sweccis.connections["registered"] == 2

    @pytest.mark.anyio
    async def test_an_order_sent_again_is_acknowledged_duplicate_not_republished(
        self, tmp_path: Path
    ) -> None:
        intake = Intake()
        async with SweccisPeer(tmp_path) as peer:
            sweccis = source(peer, intake)
            with anyio.fail_after(10):
                async with running(sweccis, peer):
                    await peer.push_order(order_document("doc-1", "ORD-1"))
                    await eventually(acked(peer, 1))
                    await peer.push_order(order_document("doc-1", "ORD-1"))
                    await eventually(acked(peer, 2))
        assert len(intake.events) == 1
        assert [status for _, status, _ in peer.order_acks] == ["accepted", "duplicate"]

    @pytest.mark.anyio
    async def test_one_order_under_many_document_ids_is_published_once(
        self, tmp_path: Path
    ) -> None:
        intake = Intake()
        async with SweccisPeer(tmp_path) as peer:
            sweccis = source(peer, intake)
            with anyio.fail_after(10):
                async with running(sweccis, peer):
                    for n in range(5):
                        await peer.push_order(order_document(f"doc-{n}", "ORD-1"))
                    await eventually(acked(peer, 5))
        assert [e.event_id for e in intake.events] == ["sweccis-order-ORD-1"]
        assert [status for _, status, _ in peer.order_acks] == ["accepted"] + ["duplicate"] * 4

    @pytest.mark.anyio
    async def test_a_changed_order_under_a_taken_id_is_a_conflict(self, tmp_path: Path) -> None:
        """ORD-1 again with another point: rejected, an OrderStatus conflict; the first stands."""
        intake = Intake()
        async with SweccisPeer(tmp_path) as peer:
            sweccis = source(peer, intake)
            with anyio.fail_after(10):
                async with running(sweccis, peer):
                    await peer.push_order(order_document("doc-1", "ORD-1", point=(65.85, 21.1)))
                    await eventually(acked(peer, 1))
                    await peer.push_order(order_document("doc-2", "ORD-1", point=(65.9, 21.2)))
                    await eventually(lambda: peer.order_statuses("ORD-1") == ["conflict"])
        assert len(intake.events) == 1
        assert [status for _, status, _ in peer.order_acks] == ["accepted", "rejected"]
        assert peer.order_acks[1][2] == (
            "order_id: ORD-1 was already taken with other content; the first stands: give a"
            " changed order a new id"
        )
        assert peer.invalid == []  # the conflict status passed the shipped XSD
        assert sweccis.counts["conflict"] == 1


class TestHostileInput:
    """Bad orders are rejected by name, garbage is counted; the source carries on."""

    @pytest.mark.anyio
    async def test_a_bad_order_is_rejected_naming_the_element_and_logged_once(
        self, tmp_path: Path
    ) -> None:
        intake = Intake()
        async with SweccisPeer(tmp_path) as peer:
            sweccis = source(peer, intake)
            with anyio.fail_after(10), capture_logs() as logs:
                async with running(sweccis, peer):
                    for n in range(5):
                        await peer.push_order(order_document(f"bad-{n}", "O", mgrs="34W IA 1 2"))
                    await peer.push_order(order_document("good", "O-good"))
                    await eventually(acked(peer, 6))
        assert [e.event_id for e in intake.events] == ["sweccis-order-O-good"]
        for ref, status, reason in peer.order_acks[:5]:
            assert ref.startswith("bad-")
            assert status == "rejected"
            assert reason is not None
            assert reason.startswith("Orders/FiveLineOrder/Location/Mgrs: ")
        assert sweccis.counts["rejected"] == 5
        refused = [e for e in logs if e["event"] == "sweccis_order_refused"]
        assert len(refused) == 1  # five rejections, one log record in the interval
        assert "34W IA" not in str(refused[0]["doc_id"])

    @pytest.mark.anyio
    @pytest.mark.parametrize(
        ("frame", "outcome"),
        [
            (b"\x00\x01\x02garbage", "invalid"),
            (b"<Orders xmlns='urn:fischer-gateway:sweccis:fas:1' version='1'/>", "invalid"),
            (b"", "invalid"),
            (
                b"<Ack xmlns='urn:fischer-gateway:sweccis:fas:1' version='1' ref='x' "
                b"status='accepted'/>",
                "unexpected",
            ),
        ],
        ids=["binary", "no-id", "empty", "ack"],
    )
    async def test_frames_that_are_no_order_are_counted_and_the_link_stays(
        self, tmp_path: Path, frame: bytes, outcome: str
    ) -> None:
        intake = Intake()
        async with SweccisPeer(tmp_path) as peer:
            sweccis = source(peer, intake)
            with anyio.fail_after(10):
                async with running(sweccis, peer):
                    await peer.push_raw(frame)
                    await peer.push_order(order_document("doc-1", "ORD-1"))
                    await eventually(acked(peer, 1))
        assert sweccis.counts == {outcome: 1, "accepted": 1}
        assert sweccis.connections == {"registered": 1}

    @pytest.mark.anyio
    async def test_an_oversize_frame_ends_the_connection_not_the_source(
        self, tmp_path: Path
    ) -> None:
        intake = Intake()
        async with SweccisPeer(tmp_path) as peer:
            sweccis = source(peer, intake, max_frame_bytes=4096)
            with anyio.fail_after(10):
                async with running(sweccis, peer):
                    await peer.push_raw(b"", header=struct.pack(">I", 1 << 31))
                    await eventually(lambda: sweccis.connections["registered"] == 2)
                    await peer.push_order(order_document("doc-1", "ORD-1"))
                    await eventually(acked(peer, 1))
        assert sweccis.counts == {"oversize": 1, "accepted": 1}
        assert sweccis.connections == {"registered": 2, "lost": 1}
        assert "exceeds the 4096-byte limit" in sweccis.last_error

    @pytest.mark.anyio
    async def test_a_server_down_or_refusing_is_retried_with_backoff(self, tmp_path: Path) -> None:
        intake = Intake()
        async with SweccisPeer(tmp_path, refuse_registration="not enrolled") as peer:
            peer.is_down = True
            sweccis = source(peer, intake)
            with anyio.fail_after(10):
                async with anyio.create_task_group() as tg:
                    await tg.start(sweccis.run)
                    await eventually(lambda: sweccis.connections["failed"] >= 2)
                    peer.is_down = False
                    await eventually(lambda: "not enrolled" in sweccis.last_error)
                    peer.refuse_registration = None
                    await eventually(lambda: sweccis.state == "connected")
                    tg.cancel_scope.cancel()
        assert sweccis.connections["registered"] == 1
        assert sweccis.status()["state"] == "connected"


class TestConfig:
    """The TLS files are read when the source is built: a config error, not a loop."""

    def test_a_missing_ca_is_named_when_built(self, tmp_path: Path) -> None:
        peer = SweccisPeer(tmp_path)
        missing = tmp_path / "none.pem"
        options = peer.link_options(uri="tls://127.0.0.1:9", ca_file=str(missing))
        config = SweccisSourceConfig.model_validate(options)
        with pytest.raises(ValueError, match=str(missing)):
            SweccisSource("s", config, Intake().publish)

    def test_the_options_sit_beside_name_and_type(self, tmp_path: Path) -> None:
        options = SweccisPeer(tmp_path).link_options(uri="tls://127.0.0.1:9")
        config = SweccisSourceConfig.model_validate({"name": "x", "type": "sweccis", **options})
        assert (config.name, config.type) == ("x", "sweccis")
