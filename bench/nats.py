"""Scale-out benchmark: detections from node b to node a over NATS JetStream.

Reproducible: ``python bench/nats.py`` (``--help`` for options). Prints a Markdown table.

Two real nats-servers on loopback, each with JetStream in its own domain: hub ``a`` and
leaf ``b`` joined by a leafnode connection, as docs/scale-out.md lays out a division and a
brigade node. In the same run:

* **nats-py acked publish** (the peer): ``js.publish_async`` of ``--events`` detection
  bodies with ``Nats-Msg-Id`` to a stream on node b like its detections stream (sourced by
  no one, so node a has nothing of it to take), then waiting for every ack:
  nats-py's own pipelined, acknowledged publish rate on this machine;
* **gateway b → a**: the ``nats`` sink on b sends the same number of Detection events in
  batches of ``--batch`` (each batch published at once, every ack awaited, as the sink
  runner calls it), and the ``nats`` source on a takes them from its aggregate stream onto a
  bus callback: events/s from the first send to the last event taken at a;
* **latency at 10 % load**: the sink sends one event at a time at a tenth of the gateway
  rate just measured; latency is from ``send`` at b to the bus callback at a (p50, p99).

The source at a acknowledges what it took once a real spool (``Spool``, a file in the run's
temporary folder) committed its ids, as in the daemon (``--no-spool``: at once, as the
figures before 2026-11-27 were measured). The three measures run in turn ``--repeat`` times
(3) and the medians are printed with each round's ratio and p99: the peer's own rate varies
by a third from run to run on a loaded machine.

Not measured here: the daemon around the sink and source (spool, sink runner, routes);
``tests/e2e/test_nats_scale_out_run.py`` runs that through ``fischer-gateway run``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import multiprocessing
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from multiprocessing.connection import Connection
from pathlib import Path

# This file is named nats.py: run as a script, its folder would shadow the nats package.
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))  # the project's packages first (tests/sinks is no sinks)
sys.path.append(str(_HERE.parent / "tests"))

import anyio  # noqa: E402
import nats  # noqa: E402
from nats.js.api import DiscardPolicy, StorageType, StreamConfig  # noqa: E402
from nats.js.errors import BadRequestError  # noqa: E402
from nats_server import NatsServer  # noqa: E402 - the tests' server helper

from gateway.events import Detection, Event, Position, Sensor  # noqa: E402
from gateway.spool.store import Spool  # noqa: E402
from sinks.nats.sink import NatsSink, NatsSinkConfig  # noqa: E402
from sinks.nats.source import NatsSource, NatsSourceConfig  # noqa: E402
from sinks.nats.subjects import encode_event, subject_for  # noqa: E402


def detections(count: int, prefix: str) -> list[Detection]:
    now = datetime.now(UTC)
    return [
        Detection(
            event_id=f"{prefix}-det-{n}",
            airframe=f"B-{n % 40:02d}",
            time=now,
            sensor=Sensor.EO,
            object_class="loitering_munition",
            confidence=0.85,
            position=Position(lat_deg=65.8 + n * 1e-6, lon_deg=21.7, alt_msl_m=250.0),
            sigma_h_m=8.0,
        )
        for n in range(count)
    ]


async def peer_rate(url: str, events: list[Detection]) -> float:
    """nats-py's own pipelined acked publish into a stream like node b's, events/s.

    The stream (``PEER``, ``peer.>``) has the detections stream's settings but is sourced by
    no one: what the peer publishes must not queue before the next gateway run at node a.
    """
    nc = await nats.connect(url)
    js = nc.jetstream()
    like = StreamConfig(  # as sinks.nats.streams.events_stream makes node b's
        name="PEER",
        subjects=["peer.>"],
        storage=StorageType.FILE,
        discard=DiscardPolicy.OLD,
        max_age=3600.0,
        max_bytes=1 << 30,
        duplicate_window=600.0,
    )
    with contextlib.suppress(BadRequestError):  # made by an earlier round
        await js.add_stream(like)
    bodies = [
        (subject_for("peer", e).replace("fsg.", "", 1), encode_event(e), e.event_id) for e in events
    ]
    start = time.perf_counter()
    futures = [
        await js.publish_async(subject, body, headers={"Nats-Msg-Id": msg_id})
        for subject, body, msg_id in bodies
    ]
    await asyncio.gather(*futures)
    elapsed = time.perf_counter() - start
    await nc.close()
    return len(events) / elapsed


async def take_at_a(
    hub: str, ids: set[str], spool_path: Path | None, ready: Callable[[], None]
) -> dict[str, float]:
    """Node a: the ``nats`` source (acking once its spool committed) until every id of
    ``ids`` was taken; when each was (``time.perf_counter``: one clock for every process)."""
    taken_at: dict[str, float] = {}
    done = anyio.Event()

    def taken(event: Event) -> bool:
        if event.event_id in ids and event.event_id not in taken_at:
            taken_at[event.event_id] = time.perf_counter()
            if len(taken_at) == len(ids):
                done.set()
        return True

    source = NatsSource(
        "bench",
        NatsSourceConfig(node="a", servers=[hub], remotes=["b"], durable="bench"),
        taken,
        clock=lambda: datetime.now(UTC),
    )
    spool = None if spool_path is None else Spool(spool_path)
    if spool is not None:
        source.set_ledger(spool)
    async with anyio.create_task_group() as tasks:
        await tasks.start(source.run)
        await anyio.sleep(1.0)  # the consumer and the sourcing are up
        ready()
        with anyio.fail_after(120):
            await done.wait()
        tasks.cancel_scope.cancel()
    if spool is not None:
        spool.close()
    return taken_at


def _node_a(hub: str, ids: set[str], spool_path: Path | None, conn: Connection) -> None:
    """Node a in a process of its own: says ready, then sends when each id was taken."""
    conn.send(anyio.run(take_at_a, hub, ids, spool_path, lambda: conn.send("ready")))


async def gateway_run(
    leaf: str,
    hub: str,
    events: list[Detection],
    batch: int,
    paced_hz: float | None,
    spool_path: Path | None,
    *,
    processes: bool,
) -> tuple[float, list[float]]:
    """The sink at b, the source at a (in its own process with ``processes``, as on its
    own node; else in this one): (events/s, latencies in ms)."""
    sent_at: dict[str, float] = {}
    ids = {e.event_id for e in events}
    ready = anyio.Event()
    result: list[dict[str, float]] = []
    sink = NatsSink("bench", NatsSinkConfig(node="b", servers=[leaf]))
    await sink.open()
    async with anyio.create_task_group() as tasks:
        if processes:
            context = multiprocessing.get_context("spawn")
            ours, theirs = context.Pipe()
            node_a = context.Process(target=_node_a, args=(hub, ids, spool_path, theirs))
            node_a.start()
            assert await anyio.to_thread.run_sync(ours.recv) == "ready"

            async def collect() -> None:
                result.append(await anyio.to_thread.run_sync(ours.recv))
                node_a.join()

            tasks.start_soon(collect)
        else:

            async def in_process() -> None:
                result.append(await take_at_a(hub, ids, spool_path, ready.set))

            tasks.start_soon(in_process)
            await ready.wait()
        start = time.perf_counter()
        if paced_hz is None:
            for i in range(0, len(events), batch):
                chunk = events[i : i + batch]
                now = time.perf_counter()
                for event in chunk:
                    sent_at[event.event_id] = now
                await sink.send(chunk)
        else:
            interval = 1.0 / paced_hz
            for n, event in enumerate(events):
                delay = start + n * interval - time.perf_counter()
                if delay > 0:
                    await anyio.sleep(delay)
                sent_at[event.event_id] = time.perf_counter()
                await sink.send([event])
    await sink.aclose()
    taken_at = result[0]
    elapsed = max(taken_at.values()) - start
    return len(events) / elapsed, [(taken_at[i] - sent_at[i]) * 1000 for i in sent_at]


def p(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=20_000, help="detections per run")
    parser.add_argument("--batch", type=int, default=256, help="events per sink send")
    parser.add_argument("--paced", type=int, default=2000, help="events in the 10 %% load run")
    parser.add_argument(
        "--one-process",
        action="store_true",
        help="node a's source in the sink's process (the figures before 2026-11-27); by "
        "default it runs in a process of its own, as on its own node",
    )
    parser.add_argument(
        "--repeat", type=int, default=3, help="rounds of gateway, peer and paced runs, in turn"
    )
    parser.add_argument(
        "--no-spool",
        action="store_true",
        help="the source acks at once (no spool at node a: the figures before 2026-11-27)",
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        hub = NatsServer(Path(tmp), "a", hub=True)
        leaf = NatsServer(Path(tmp), "b", leaf_of=f"nats-leaf://127.0.0.1:{hub.leaf_port}")
        with hub, leaf:
            while not hub.leafz().get("leafs"):
                time.sleep(0.02)

            def spool(run: str) -> Path | None:
                return None if args.no_spool else Path(tmp) / f"a-{run}.spool.db"

            processes = not args.one_process

            async def run() -> list[tuple[float, float, list[float], float]]:
                rounds = []
                for n in range(args.repeat):
                    # The sink creates b's streams; then the peer publishes beside them.
                    events = detections(args.events, f"g{n}")
                    rate, _ = await gateway_run(
                        leaf.url,
                        hub.url,
                        events,
                        args.batch,
                        None,
                        spool(f"g{n}"),
                        processes=processes,
                    )
                    peer = await peer_rate(leaf.url, detections(args.events, f"p{n}"))
                    load = rate * 0.10
                    paced = detections(args.paced, f"l{n}")
                    _, lat = await gateway_run(
                        leaf.url, hub.url, paced, 1, load, spool(f"l{n}"), processes=processes
                    )
                    rounds.append((rate, peer, lat, load))
                return rounds

            rounds = anyio.run(run)
    print(
        f"nats bench: {platform.python_implementation()} {platform.python_version()}, "
        f"{args.events} detections, batch {args.batch}, {args.repeat} rounds (median), "
        f"{'no spool' if args.no_spool else 'acked once the spool at a committed'}, "
        f"{'one process' if args.one_process else 'node a in its own process'}\n"
    )
    rate = statistics.median(r[0] for r in rounds)
    peer = statistics.median(r[1] for r in rounds)
    ratios = ", ".join(f"{r[0] / r[1]:.0%}" for r in rounds)
    p99s = ", ".join(f"{p(r[2], 0.99):.1f}" for r in rounds)
    load = statistics.median(r[3] for r in rounds)
    lat = [ms for r in rounds for ms in r[2]]
    print("| measure | value |")
    print("| --- | --- |")
    print(f"| nats-py acked pipelined publish (peer) | {peer:,.0f} events/s |")
    print(f"| gateway b → a (sink, leaf, source) | {rate:,.0f} events/s |")
    print(
        f"| gateway / peer, each round | {statistics.median(r[0] / r[1] for r in rounds):.0%}"
        f" ({ratios}) |"
    )
    print(f"| latency at 10 % load ({load:,.0f}/s): p50 | {statistics.median(lat):.2f} ms |")
    print(f"| latency at 10 % load: p99 of all rounds | {p(lat, 0.99):.2f} ms |")
    print(f"| latency at 10 % load: p99 each round | {p99s} ms |")


if __name__ == "__main__":
    main()
