"""Pulling a durable consumer (``sinks.nats.pull``) against a real nats-server per test.

A message that comes after the consumer sat idle past its pull requests' expiry is handed on
by itself, at once: never held until a whole batch has come (nats-py's ``fetch`` did that
after reading a late ``408`` as the answer to its next request). An end status of an earlier
request does not end the open one, and a burst arrives whole, in order, once, in batches of
at most ``batch``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import anyio
import nats
import pytest
from daemon_support import free_tcp_port
from nats.aio.client import Client
from nats.js.api import AckPolicy, ConsumerConfig, StreamConfig
from nats_server import DEBIAN_NATS_SERVER, NEEDS_DEBIAN_NATS, NEEDS_NATS, NatsServer

from sinks.nats.pull import Puller

pytestmark = NEEDS_NATS

#: A guard against a hang, not a measure of speed.
HANG_S = 30


@pytest.fixture(
    params=[
        pytest.param(None, id="current"),
        pytest.param(DEBIAN_NATS_SERVER, id="debian-2.9", marks=NEEDS_DEBIAN_NATS),
    ]
)
def server(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[NatsServer]:
    with NatsServer(tmp_path, "a", binary=request.param) as running:
        yield running


async def consumer(url: str) -> Client:
    nc = await nats.connect(url)
    js = nc.jetstream()
    await js.add_stream(StreamConfig(name="S", subjects=["s.>"]))
    await js.add_consumer(
        "S", config=ConsumerConfig(durable_name="d", ack_policy=AckPolicy.EXPLICIT)
    )
    return nc


def test_a_message_after_an_idle_spell_is_handed_on_alone(server: NatsServer) -> None:
    async def main() -> tuple[list[int], int]:
        nc = await consumer(server.url)
        puller = Puller(nc, "S", "d", batch=256, wait_s=0.2)
        sizes: list[int] = []
        async with anyio.create_task_group() as tasks:
            tasks.start_soon(puller.run)
            # Idle for several expiries: their 408s race the next requests.
            while puller.requests < 6:  # noqa: ASYNC110 - the puller's own count
                await anyio.sleep(0.05)
            # An end status of an earlier request, come late: it must not end the open one.
            stale = int(puller._open) - 1
            await nc.publish(f"{puller._inbox}.{stale}", b"", headers={"Status": "408"})
            for n in range(3):
                # One message, then the next only once the first was handed on: a puller
                # that held it for a full batch (255 more) would hang here.
                await nc.jetstream().publish(f"s.{n}", str(n).encode())
                with anyio.fail_after(HANG_S):
                    batch = await puller.next_batch()
                sizes.append(len(batch))
                for message in batch:
                    await message.ack()
                await anyio.sleep(0.5)  # idle past the expiry again
            requests = puller.requests
            tasks.cancel_scope.cancel()
        await nc.close()
        return sizes, requests

    sizes, requests = anyio.run(main)
    assert sizes == [1, 1, 1]
    assert requests > 6


def test_a_burst_arrives_whole_in_order_once_in_bounded_batches(server: NatsServer) -> None:
    async def main() -> list[list[bytes]]:
        nc = await consumer(server.url)
        js = nc.jetstream()
        for n in range(1000):
            await js.publish_async(f"s.{n % 7}", str(n).encode())
        await js.publish_async_completed()
        puller = Puller(nc, "S", "d", batch=64, wait_s=0.5)
        batches: list[list[bytes]] = []
        async with anyio.create_task_group() as tasks:
            tasks.start_soon(puller.run)
            with anyio.fail_after(HANG_S):
                while sum(map(len, batches)) < 1000:
                    batch = await puller.next_batch()
                    batches.append([message.data for message in batch])
                    for message in batch:
                        await message.ack()
            await anyio.sleep(0.6)  # anything more (a repeat) would come now
            assert not puller._buffer
            tasks.cancel_scope.cancel()
        await nc.close()
        return batches

    batches = anyio.run(main)
    assert [int(body) for batch in batches for body in batch] == list(range(1000))
    assert max(map(len, batches)) <= 64


def test_pulling_goes_on_after_the_server_restarts(tmp_path: Path) -> None:
    """The open pull request is lost with the server; the next one, sent once it expired
    here, takes what was published since (the consumer lives in the server's store)."""
    with NatsServer(tmp_path, "a", port=free_tcp_port()) as server:

        async def main() -> list[bytes]:
            nc = await consumer(server.url)
            puller = Puller(nc, "S", "d", batch=16, wait_s=0.2)
            taken: list[bytes] = []
            async with anyio.create_task_group() as tasks:
                tasks.start_soon(puller.run)
                await nc.jetstream().publish("s.1", b"before")
                with anyio.fail_after(HANG_S):
                    batch = await puller.next_batch()
                taken += [message.data for message in batch]
                await batch[0].ack()
                await anyio.to_thread.run_sync(server.stop)
                await anyio.to_thread.run_sync(server.start)
                with anyio.fail_after(HANG_S):
                    while not nc.is_connected:  # noqa: ASYNC110 - nats-py's own reconnect
                        await anyio.sleep(0.05)
                    await nc.jetstream().publish("s.2", b"after")
                    batch = await puller.next_batch()
                taken += [message.data for message in batch]
                tasks.cancel_scope.cancel()
            await nc.close()
            return taken

        assert anyio.run(main) == [b"before", b"after"]
