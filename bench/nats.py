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
import dataclasses
import platform
import statistics
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

# This file is named nats.py: run as a script, its folder would shadow the nats package.
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))  # the project's packages first (tests/sinks is no sinks)
sys.path.append(str(_HERE.parent / "tests"))

import anyio  # noqa: E402
import nats  # noqa: E402
from nats.js.errors import BadRequestError  # noqa: E402
from nats_server import NatsServer  # noqa: E402 - the tests' server helper

from gateway.events import Detection, Event, EventKind, Position, Sensor  # noqa: E402
from gateway.spool.store import Spool  # noqa: E402
from sinks.nats.sink import NatsSink, NatsSinkConfig  # noqa: E402
from sinks.nats.source import NatsSource, NatsSourceConfig  # noqa: E402
from sinks.nats.streams import events_stream  # noqa: E402
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
    like = events_stream("b", {EventKind.DETECTION}, 3600.0, 1 << 30, 600.0)
    with contextlib.suppress(BadRequestError):  # made by an earlier round
        await js.add_stream(dataclasses.replace(like, name="PEER", subjects=["peer.>"]))
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


async def gateway_run(
    leaf: str,
    hub: str,
    events: list[Detection],
    batch: int,
    paced_hz: float | None,
    spool: Spool | None,
) -> tuple[float, list[float]]:
    """The sink at b, the source at a (acking once ``spool`` committed): (events/s, ms)."""
    sent_at: dict[str, float] = {}
    latencies: list[float] = []
    done = anyio.Event()
    wanted = {e.event_id for e in events}

    def taken(event: Event) -> bool:
        if event.event_id in wanted:
            latencies.append((time.perf_counter() - sent_at[event.event_id]) * 1000)
            if len(latencies) == len(wanted):
                done.set()
        return True

    sink = NatsSink("bench", NatsSinkConfig(node="b", servers=[leaf]))
    source = NatsSource(
        "bench",
        NatsSourceConfig(node="a", servers=[hub], remotes=["b"], durable="bench"),
        taken,
        clock=lambda: datetime.now(UTC),
    )
    if spool is not None:
        source.set_ledger(spool)
    await sink.open()
    async with anyio.create_task_group() as tasks:
        await tasks.start(source.run)
        await anyio.sleep(1.0)  # the consumer and the sourcing are up
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
        with anyio.fail_after(120):
            await done.wait()
        elapsed = time.perf_counter() - start
        tasks.cancel_scope.cancel()
    await sink.aclose()
    return len(events) / elapsed, latencies


def p(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=20_000, help="detections per run")
    parser.add_argument("--batch", type=int, default=256, help="events per sink send")
    parser.add_argument("--paced", type=int, default=2000, help="events in the 10 %% load run")
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

            spool = None if args.no_spool else Spool(Path(tmp) / "a.spool.db")

            async def run() -> list[tuple[float, float, list[float], float]]:
                rounds = []
                for n in range(args.repeat):
                    # The sink creates b's streams; the peer publishes into the same one.
                    events = detections(args.events, f"g{n}")
                    rate, _ = await gateway_run(leaf.url, hub.url, events, args.batch, None, spool)
                    peer = await peer_rate(leaf.url, detections(args.events, f"p{n}"))
                    load = rate * 0.10
                    paced = detections(args.paced, f"l{n}")
                    _, lat = await gateway_run(leaf.url, hub.url, paced, 1, load, spool)
                    rounds.append((rate, peer, lat, load))
                return rounds

            rounds = anyio.run(run)
    print(
        f"nats bench: {platform.python_implementation()} {platform.python_version()}, "
        f"{args.events} detections, batch {args.batch}, {args.repeat} rounds (median), "
        f"{'no spool' if args.no_spool else 'acked once the spool at a committed'}\n"
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
