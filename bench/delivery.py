"""Delivery benchmark: in-process ``Bus.publish`` -> the last of five sinks, with the file spool.

Reproducible: ``python bench/delivery.py`` (``--help`` for options; ``--before REF`` also runs
the same measurement on another commit, interleaved, each run in a fresh process with that
tree's code first on the path). Prints a Markdown table.

Two measurements, both on the real ``Bus``, ``SinkRunner`` and ``Spool`` (file, WAL,
``synchronous=NORMAL``), five sinks that stamp each event on arrival, on the asyncio loop:

* **latency**: one detection published per loop pass, the next only once the last of the five
  sinks has it; p50/p99 of publish -> arrival at the last sink (``perf_counter``);
* **spooled events/s**: ``--burst`` detections published per loop pass, then the pass's
  commit, the runners not started (what ``bench/spool.py`` calls the spool's rate: the JSON
  body once, an owed row per sink, one commit per burst), routed to five sinks and to two
  (``bench/spool.py``'s default). Its peer: plain sqlite3 on a WAL file with the same
  ``synchronous``, the same events' JSON inserted one ``INSERT`` per event and one
  ``COMMIT`` per burst (batched the same way). The three are run burst by burst, interleaved,
  and each side's CPU time (``process_time``) is summed: a ratio the machine's load cancels
  out of (the prepared events are frozen out of the cyclic collector first: a full collection
  of them fell on one side or another at random, a swing of 0.3 in the ratio);
* **delivered events/s**: the same bursts with the five runners running, until the last sink
  has the last event and every confirmation is committed (the spool owes nothing), per
  second of the process's CPU time.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import platform
import shutil
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GIT = shutil.which("git") or "git"
SINKS = 5


def _events(n: int, tag: str) -> list[object]:
    from datetime import UTC, datetime

    from gateway.events import Detection, Position, Sensor

    t0 = datetime(2026, 11, 23, 12, 0, tzinfo=UTC)
    return [
        Detection(
            event_id=f"F26E-001-det-{tag}-{i}",
            airframe="F26E-001",
            time=t0,
            sensor=Sensor.EO,
            object_class="tank",
            subtype="T-72",
            confidence=0.91,
            position=Position(lat_deg=58.41 + i * 1e-6, lon_deg=15.62, alt_msl_m=95.0),
            sigma_h_m=8.0,
        )
        for i in range(n)
    ]


class StampSink:
    """Records when each event arrives; wakes the bench when the expected count is in."""

    def __init__(self, name: str, kinds: frozenset[object]) -> None:
        self.name = name
        self.kinds = kinds
        self.count = 0
        self.arrived: dict[str, float] = {}
        self.target = 0
        self.done: asyncio.Future[None] | None = None

    async def open(self) -> None:
        """Nothing to open."""

    async def send(self, batch: Sequence[object]) -> None:
        now = time.perf_counter()
        for event in batch:
            self.arrived[event.event_id] = now  # type: ignore[attr-defined]
        self.count += len(batch)
        if self.count >= self.target and self.done is not None and not self.done.done():
            self.done.set_result(None)

    async def aclose(self) -> None:
        """Nothing to close."""


async def _run(spool_dir: Path, latency_events: int, events: int, burst: int) -> dict[str, float]:
    import anyio

    from gateway.c2.sinkrunner import SinkRunner
    from gateway.config import RouteConfig, SinkEntry
    from gateway.events import EventKind
    from gateway.flow.bus import Bus
    from gateway.ops.instruments import Instruments
    from gateway.spool.store import Spool

    spool = Spool(spool_dir / "spool.db")
    inst = Instruments()
    names = [f"s{i}" for i in range(SINKS)]
    sinks = {name: StampSink(name, frozenset(EventKind)) for name in names}
    runners = {
        name: SinkRunner(
            SinkEntry(name=name, type="null", queue_max=10_000), sinks[name], inst, spool=spool
        )
        for name in names
    }
    bus = Bus([RouteConfig(sinks=tuple(names))], runners, inst, spool=spool)
    loop = asyncio.get_running_loop()
    out: dict[str, float] = {}
    async with anyio.create_task_group() as tg:
        for runner in runners.values():
            await tg.start(runner.run)

        async def until(count: int) -> None:
            waits = []
            for sink in sinks.values():
                sink.target = count
                sink.done = loop.create_future()
                if sink.count >= count:
                    sink.done.set_result(None)
                waits.append(sink.done)
            await asyncio.gather(*waits)

        # Latency: one event per loop pass, the next once the last sink has it.
        lat: list[float] = []
        sent = 0
        for event in _events(latency_events, "lat"):
            await asyncio.sleep(0)
            t0 = time.perf_counter()
            bus.publish(event)  # type: ignore[arg-type]
            sent += 1
            await until(sent)
            last = max(sink.arrived[event.event_id] for sink in sinks.values())  # type: ignore[attr-defined]
            lat.append(last - t0)
        warm = sorted(lat[len(lat) // 10 :] if len(lat) > 20 else lat)  # the first 10 %: warm-up
        out["p50_ms"] = statistics.median(warm) * 1e3
        out["p99_ms"] = warm[int(0.99 * (len(warm) - 1))] * 1e3
        while any(spool.pending_count(n) for n in names):  # noqa: ASYNC110 - nothing signals it
            await asyncio.sleep(0.001)

        # Throughput: ``burst`` events per loop pass.
        batch = _events(events, "thr")
        start = time.process_time()
        for i in range(0, events, burst):
            for event in batch[i : i + burst]:
                bus.publish(event)  # type: ignore[arg-type]
            await asyncio.sleep(0)
        await until(sent + events)
        while any(spool.pending_count(n) for n in names):  # noqa: ASYNC110 - nothing signals it
            await asyncio.sleep(0)
        out["events_s"] = events / (time.process_time() - start)
        for runner in runners.values():
            runner.stop()
        for runner in runners.values():
            await runner.wait_done()
    spool.close()

    # Spooled events/s (publish and the pass's commit, no runner takes them) for five sinks
    # and for two (bench/spool.py's default), and the plain sqlite3 peer: burst by burst,
    # interleaved, each side's CPU time summed, so the machine's load falls on all alike.
    db = sqlite3.connect(spool_dir / "plain.db", isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=NORMAL")
    db.execute("CREATE TABLE events (seq INTEGER PRIMARY KEY, event_id TEXT, body BLOB)")

    def plain(chunk: list[object]) -> None:
        db.execute("BEGIN")
        for event in chunk:
            body = event.model_dump_json().encode()  # type: ignore[attr-defined]
            db.execute(
                "INSERT INTO events (event_id, body) VALUES (?, ?)",
                (event.event_id, body),  # type: ignore[attr-defined]
            )
        db.execute("COMMIT")

    def spooling(fan_out: int) -> tuple[Spool, object]:
        spool = Spool(spool_dir / f"spool-{fan_out}.db")
        wanted = names[:fan_out]
        idle = {
            name: SinkRunner(
                SinkEntry(name=name, type="null", queue_max=10_000), sinks[name], inst, spool=spool
            )
            for name in wanted
        }
        bus = Bus([RouteConfig(sinks=tuple(wanted))], idle, inst, spool=spool)
        flush = getattr(spool, "flush", lambda: True)  # an older tree commits each publish

        def run(chunk: list[object]) -> None:
            for event in chunk:
                bus.publish(event)  # type: ignore[arg-type]
            flush()  # what the end of the loop pass does

        return spool, run

    spool5, run5 = spooling(SINKS)
    spool2, run2 = spooling(2)
    sides = {"spooled_s": run5, "spooled2_s": run2, "sqlite_events_s": plain}
    chunks = {name: _events(events, name[:4]) for name in sides}
    # The events prepared above are the bench's, not the gateway's: frozen out of the cyclic
    # collector, so that a full collection of them (tens of ms) is not charged to whichever
    # side happens to run when it falls due.
    gc.collect()
    gc.freeze()
    cpu = dict.fromkeys(sides, 0.0)
    for i in range(0, events, burst):
        for name, side in sides.items():
            t0 = time.process_time()
            side(chunks[name][i : i + burst])  # type: ignore[operator]
            cpu[name] += time.process_time() - t0
    gc.unfreeze()
    for name in sides:
        out[name] = events / cpu[name]
    spool5.close()
    spool2.close()
    db.close()
    return out


def measure(
    latency_events: int, events: int, burst: int, *, uvloop: bool = False
) -> dict[str, float]:
    """One run in this process: latency and throughput figures (on uvloop if asked)."""
    factory = None
    if uvloop:
        import uvloop as uv

        factory = uv.new_event_loop
    with (
        tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_DIR")) as tmp,
        asyncio.Runner(loop_factory=factory) as runner,
    ):
        return runner.run(_run(Path(tmp), latency_events, events, burst))


def _in_tree(tree: Path, args: argparse.Namespace) -> dict[str, float]:
    """Run ``measure`` of this file with ``tree``'s gateway first on the path."""
    bench = str(ROOT / "bench")
    code = (
        f"import sys; sys.path.insert(0, {str(tree)!r}); sys.path.insert(1, {bench!r})\n"
        "import json, delivery\n"
        "from gateway.ops.logsetup import configure_logging\n"
        "configure_logging('warning', sys.stderr)\n"
        f"print(json.dumps(delivery.measure({args.latency_events}, {args.events}, "
        f"{args.burst}, uvloop={args.uvloop})))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tree, env=env, capture_output=True, text=True, check=True
    )
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--latency-events", type=int, default=2_000)
    parser.add_argument("--events", type=int, default=20_000)
    parser.add_argument("--burst", type=int, default=100, help="events published per loop pass")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--before", help="a commit to compare with, interleaved in this run")
    parser.add_argument("--uvloop", action="store_true", help="on uvloop, as the daemon runs")
    args = parser.parse_args()
    trees: dict[str, Path] = {"this tree": ROOT}
    tmp = None
    if args.before:
        tmp = Path(tempfile.mkdtemp())
        subprocess.run(
            [GIT, "worktree", "add", "--detach", str(tmp / "before"), args.before],
            cwd=ROOT, check=True, capture_output=True,
        )  # fmt: skip
        trees = {f"before ({args.before})": tmp / "before", **trees}
    results: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    try:
        for _ in range(args.rounds):
            for name, tree in trees.items():
                results[name].append(_in_tree(tree, args))
    finally:
        if tmp is not None:
            subprocess.run(
                [GIT, "worktree", "remove", "--force", str(tmp / "before")],
                cwd=ROOT, check=False, capture_output=True,
            )  # fmt: skip
            shutil.rmtree(tmp, ignore_errors=True)
    print(
        f"{platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"SQLite {sqlite3.sqlite_version}, {'uvloop' if args.uvloop else 'asyncio'}, "
        f"{SINKS} sinks, file spool (NORMAL), "
        f"{args.rounds} rounds (median [min-max])\n"
    )
    print(
        "| tree | p50 ms | p99 ms | sqlite3 WAL ev/s | spooled ev/s, 5 sinks | ÷ sqlite3 "
        "| spooled, 2 sinks | ÷ sqlite3 | delivered ev/s, 5 sinks | ÷ sqlite3 |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")

    def cell(values: list[float], fmt: str) -> str:
        return f"{statistics.median(values):{fmt}} [{min(values):{fmt}}-{max(values):{fmt}}]"

    for name, runs in results.items():

        def ratio(key: str, runs: list[dict[str, float]] = runs) -> str:
            return cell([r[key] / r["sqlite_events_s"] for r in runs], ".2f")

        print(
            f"| {name} | {cell([r['p50_ms'] for r in runs], '.3f')} "
            f"| {cell([r['p99_ms'] for r in runs], '.3f')} "
            f"| {cell([r['sqlite_events_s'] for r in runs], ',.0f')} "
            f"| {cell([r['spooled_s'] for r in runs], ',.0f')} | {ratio('spooled_s')} "
            f"| {cell([r['spooled2_s'] for r in runs], ',.0f')} | {ratio('spooled2_s')} "
            f"| {cell([r['events_s'] for r in runs], ',.0f')} | {ratio('events_s')} |"
        )


if __name__ == "__main__":
    main()
