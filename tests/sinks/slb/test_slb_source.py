"""The slb order source against a real HTTPS SLB (SlbPeer) on loopback."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import anyio
import httpx
import pytest
import trustme
from slb_peer import SlbPeer
from structlog.testing import capture_logs

from gateway.events import Event, FiveLineOrder, OrderTask
from gateway.testing import eventually
from gateway.transports.https import https_client
from sinks.slb.source import SlbSource, SlbSourceConfig

NOW = datetime(2026, 11, 22, 12, 0, 30, tzinfo=UTC)


def order(order_id: str, **change: Any) -> dict[str, Any]:
    return {
        "order_id": order_id,
        "issuer": "2 MekB S3",
        "issued": "2026-11-22T12:00:00Z",
        "task": "recon_area",
        "location": {
            "polygon": [
                {"lat_deg": 65.80, "lon_deg": 21.60},
                {"lat_deg": 65.85, "lon_deg": 21.60},
                {"lat_deg": 65.85, "lon_deg": 21.70},
            ]
        },
        "priority": "priority",
        **change,
    }


class Published:
    """The source's ``publish``: keeps what it is given; refuses while ``refuse`` is True."""

    def __init__(self) -> None:
        self.events: list[Event] = []
        self.refuse = False
        self.offers = 0

    def __call__(self, event: Event) -> bool:
        self.offers += 1
        if self.refuse:
            return False
        self.events.append(event)
        return True

    @property
    def orders(self) -> list[FiveLineOrder]:
        return [e for e in self.events if isinstance(e, FiveLineOrder)]


def source_for(peer: SlbPeer, publish: Published, **options: Any) -> SlbSource:
    config = SlbSourceConfig.model_validate(peer.source_options(**options))
    return SlbSource("brigade-slb", config, publish, clock=lambda: NOW)


@asynccontextmanager
async def client_for(source: SlbSource) -> AsyncIterator[httpx.AsyncClient]:
    client = await https_client(
        source.config.tls_files,
        connect_timeout_s=5,
        read_timeout_s=5,
        write_timeout_s=5,
        pool_timeout_s=5,
    )
    async with client:
        yield client


async def running(source: SlbSource, done: Callable[[], bool]) -> None:
    """Run the source (its own ``run``) until ``done()``."""
    async with anyio.create_task_group() as tg:
        await tg.start(source.run)
        await eventually(done)
        tg.cancel_scope.cancel()


class TestOrders:
    """An order is published as a FiveLineOrder, then acknowledged as received."""

    @pytest.mark.anyio
    async def test_an_order_arrives_and_its_receipt_reaches_slb(self, tmp_path: Path) -> None:
        published = Published()
        async with SlbPeer(tmp_path) as peer:
            peer.queue_order(order("O-1", location={"mgrs": "34W EU 31783 00413"}))
            source = source_for(peer, published, poll_interval_s=0.05)
            with anyio.fail_after(10):
                await running(source, lambda: bool(peer.receipts))
        (event,) = published.orders
        assert event.event_id == "slb-order-O-1"
        assert event.source == "brigade-slb"
        assert event.task is OrderTask.RECON_AREA
        assert event.location.mgrs == "34W EU 31783 00413"
        (receipt,) = peer.receipts
        assert receipt == {
            "order_id": "O-1",
            "status": "received",
            "reason": None,
            "event_id": "slb-order-O-1",
            "time": "2026-11-22T12:00:30.000Z",
            "seq": None,
        }
        assert peer.orders == {}  # SLB stops offering it
        gets = [r for r in peer.requests if r.method == "GET"]
        assert gets[0].path == "/slb/api/orders"
        assert gets[0].query == {"limit": ["100"]}
        assert source.status()["counts"]["received"] == 1

    @pytest.mark.anyio
    async def test_not_held_means_no_receipt_and_it_is_taken_at_the_next_poll(
        self, tmp_path: Path
    ) -> None:
        published = Published()
        published.refuse = True
        async with SlbPeer(tmp_path) as peer:
            peer.queue_order(order("O-2"))
            source = source_for(peer, published)
            async with client_for(source) as client:
                with anyio.fail_after(10):
                    await source.poll(client)
                    assert peer.receipts == []
                    assert list(peer.orders) == ["O-2"]  # still offered
                    published.refuse = False
                    await source.poll(client)
        assert [o.order_id for o in published.orders] == ["O-2"]
        assert [r["status"] for r in peer.receipts] == ["received"]
        assert source.counts["not_held"] == 1
        assert source.counts["received"] == 1

    @pytest.mark.anyio
    async def test_a_lost_receipt_is_sent_again_and_the_order_published_once(
        self, tmp_path: Path
    ) -> None:
        published = Published()
        async with SlbPeer(tmp_path, fail_receipts=1) as peer:
            peer.queue_order(order("O-3"))
            source = source_for(peer, published)
            async with client_for(source) as client:
                with anyio.fail_after(10):
                    await source.poll(client)
                    assert peer.receipts == []  # the receipt got a 503
                    await source.poll(client)
        assert len(published.orders) == 1
        assert [r["order_id"] for r in peer.receipts] == ["O-3"]
        assert source.counts["reoffered"] == 1
        assert source.counts["receipt_failed"] == 1

    @pytest.mark.anyio
    async def test_a_changed_order_under_a_taken_id_is_a_conflict(self, tmp_path: Path) -> None:
        """SLB offers O-4 again with another area: answered conflict, not the old receipt."""
        published = Published()
        async with SlbPeer(tmp_path) as peer:
            peer.queue_order(order("O-4"))
            source = source_for(peer, published)
            async with client_for(source) as client:
                with anyio.fail_after(10):
                    await source.poll(client)
                    peer.queue_order(order("O-4"))  # the same again: its receipt again
                    await source.poll(client)
                    peer.queue_order(order("O-4", priority="flash"))  # changed
                    await source.poll(client)
        assert len(published.orders) == 1
        assert [r["status"] for r in peer.receipts] == ["received", "received", "conflict"]
        assert peer.receipts[-1]["reason"] == (
            "order_id: O-4 was already taken with other content; the first stands: give a"
            " changed order a new id"
        )
        assert source.counts["conflict"] == 1
        assert source.counts["reoffered"] == 1

    @pytest.mark.anyio
    async def test_the_limit_is_asked_for_and_the_rest_wait(self, tmp_path: Path) -> None:
        published = Published()
        async with SlbPeer(tmp_path) as peer:
            for n in range(5):
                peer.queue_order(order(f"O-{n}"))
            source = source_for(peer, published, max_orders=2)
            async with client_for(source) as client:
                with anyio.fail_after(10):
                    await source.poll(client)
                    assert [o.order_id for o in published.orders] == ["O-0", "O-1"]
                    await source.poll(client)
                    await source.poll(client)
        assert [o.order_id for o in published.orders] == [f"O-{n}" for n in range(5)]
        assert len(peer.receipts) == 5


class TestMalformed:
    """A malformed order is counted, logged once per interval and answered "rejected"."""

    @pytest.mark.anyio
    async def test_rejected_with_a_reason_naming_the_field(self, tmp_path: Path) -> None:
        published = Published()
        async with SlbPeer(tmp_path) as peer:
            peer.queue_order(order("BAD-1", task="fire_mission"))
            peer.queue_order(order("BAD-2", issued="yesterday"))
            peer.queue_order(order("BAD-3", location={"mgrs": "not a grid"}))
            peer.queue_order(order("GOOD"))
            source = source_for(peer, published)
            with capture_logs() as logs:
                async with client_for(source) as client:
                    with anyio.fail_after(10):
                        await source.poll(client)
        assert [o.order_id for o in published.orders] == ["GOOD"]
        reasons = {r["order_id"]: (r["status"], r["reason"]) for r in peer.receipts}
        assert reasons["GOOD"] == ("received", None)
        assert reasons["BAD-1"][0] == "rejected"
        assert reasons["BAD-1"][1].startswith("task: ")
        assert reasons["BAD-2"][1].startswith("issued: ")
        assert reasons["BAD-3"][1].startswith("location.mgrs: ")
        assert source.counts["rejected"] == 3
        problems = [e for e in logs if e["event"] == "slb_orders_problem"]
        assert [(e["outcome"], e["order_id"]) for e in problems] == [("rejected", "BAD-1")]

    @pytest.mark.anyio
    async def test_an_order_without_a_usable_id_is_counted_unanswerable(
        self, tmp_path: Path
    ) -> None:
        published = Published()
        async with SlbPeer(tmp_path) as peer:
            peer.queue_order({"task": "recon_area"})
            peer.queue_order(order("has/slash"))
            peer.queue_order("not an object")
            source = source_for(peer, published)
            async with client_for(source) as client:
                with anyio.fail_after(10):
                    await source.poll(client)
        assert source.counts["unanswerable"] == 3
        assert published.offers == 0
        assert peer.receipts == []

    @pytest.mark.parametrize(
        ("body", "outcome"),
        [
            (b"<html>oops</html>", "malformed_list"),
            (b'{"orders": [NaN]}', "malformed_list"),
            (b"[" * 20_000 + b"]" * 20_000, "malformed_list"),
            (b'{"orders": "none"}', "malformed_list"),
            (json.dumps({"orders": [order(f"O-{n}") for n in range(400)]}).encode(), "oversize"),
        ],
        ids=["html", "nan", "deep", "shape", "oversize"],
    )
    @pytest.mark.anyio
    async def test_a_hostile_body_is_counted_and_polling_goes_on(
        self, tmp_path: Path, body: bytes, outcome: str
    ) -> None:
        published = Published()
        async with SlbPeer(tmp_path) as peer:
            peer.orders_body = body
            source = source_for(peer, published, max_body_bytes=64 * 1024)
            async with client_for(source) as client:
                with anyio.fail_after(10):
                    assert await source.poll(client) == source.config.poll_interval_s
                    await source.poll(client)
        assert source.counts[outcome] == 2
        assert published.offers == 0


class TestPolling:
    """SLB's Retry-After, its absence, and a peer that is not who it should be."""

    @pytest.mark.anyio
    async def test_retry_after_sets_the_next_poll_bounded(self, tmp_path: Path) -> None:
        async with SlbPeer(tmp_path, busy_polls=2, retry_after="7") as peer:
            source = source_for(peer, Published(), poll_interval_s=1.0, max_retry_after_s=5.0)
            async with client_for(source) as client:
                with anyio.fail_after(10):
                    assert await source.poll(client) == 5.0  # 7 s asked, 5 s at most
                    peer.retry_after = "2"
                    assert await source.poll(client) == 2.0
                    assert await source.poll(client) == 1.0  # 204: the interval
        assert source.counts["poll_refused"] == 2

    @pytest.mark.anyio
    async def test_slb_down_is_counted_and_the_source_keeps_polling(self, tmp_path: Path) -> None:
        published = Published()
        async with SlbPeer(tmp_path) as peer:
            peer.down = True
            source = source_for(peer, published, poll_interval_s=0.02)
            with anyio.fail_after(10):
                async with anyio.create_task_group() as tg:
                    await tg.start(source.run)
                    await eventually(lambda: source.counts["poll_failed"] >= 2)
                    peer.queue_order(order("O-9"))
                    peer.down = False
                    await eventually(lambda: bool(peer.receipts))
                    tg.cancel_scope.cancel()
        assert [o.order_id for o in published.orders] == ["O-9"]

    @pytest.mark.anyio
    async def test_a_server_from_another_ca_is_never_asked(self, tmp_path: Path) -> None:
        other_ca = tmp_path / "other-ca.pem"
        trustme.CA().cert_pem.write_to_path(str(other_ca))
        async with SlbPeer(tmp_path) as peer:
            source = source_for(peer, Published(), ca_file=str(other_ca))
            with capture_logs() as logs:
                async with client_for(source) as client:
                    with anyio.fail_after(10):
                        await source.poll(client)
        assert peer.requests == []
        (line,) = [e for e in logs if e["event"] == "slb_orders_problem"]
        assert f"not trusted by the pinned CA {other_ca}" in line["detail"]


class TestConfig:
    """Unusable TLS material is a config error at construction, naming the file."""

    def test_a_missing_certificate_is_named(self, tmp_path: Path) -> None:
        peer = SlbPeer(tmp_path)
        missing = tmp_path / "nope.pem"
        config = SlbSourceConfig.model_validate(peer.source_options(cert_file=str(missing)))
        with pytest.raises(ValueError, match=str(missing)):
            SlbSource("slb", config, Published())

    def test_check_config_names_each_problem_with_its_line(self, tmp_path: Path) -> None:
        peer = SlbPeer(tmp_path)
        missing = tmp_path / "missing.pem"
        config = tmp_path / "node.yaml"
        config.write_text(
            "health: {port: 0}\n"
            "sources:\n"
            "  - name: slb_in\n"
            "    type: slb\n"
            f"    base_url: {peer.base_url}\n"
            f"    ca_file: {peer.ca_file}\n"
            f"    cert_file: {missing}\n"
            "sinks:\n"
            "  - name: slb\n"
            "    type: slb\n"
            f"    options: {{base_url: 'http://slb/api', ca_file: '{peer.ca_file}',\n"
            f"               cert_file: '{peer.cert_file}', key_file: '{peer.key_file}'}}\n"
        )
        result = subprocess.run(
            [sys.executable, "-m", "gateway", "check-config", str(config)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert result.returncode == 2
        # Validated on the node like a sink's options: the file is named on the source's line.
        assert f"{config}:3 sources[0]: {missing}" in result.stderr
        assert f"{config}:11 sinks[0].options.base_url: expected https://" in result.stderr

    def test_status(self, tmp_path: Path) -> None:
        peer = SlbPeer(tmp_path)
        source = source_for(peer, Published())
        assert source.status() == {
            "source": "brigade-slb",
            "type": "slb",
            "url": "https://127.0.0.1:0/slb/api/orders",
            "counts": {},
            "remembered": 0,
        }
