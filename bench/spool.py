"""Spool benchmark: durable events through the gateway's spool against plain sqlite3 inserts.

Reproducible: ``python bench/spool.py`` (``--help`` for options). Prints a Markdown table.

The same pre-built Detection events (``--events``) are written, in the same run, by:

* **sqlite3 plain**: one ``INSERT`` of the event's JSON and one ``COMMIT`` per event into a
  one-table WAL database with the same ``synchronous`` setting: the floor any SQLite spool
  pays, and so the peer the spool is compared with;
* **spool**: ``Bus.publish`` of each event routed to ``--sinks`` sink runners with the file
  spool (what ingest does for every detection: the JSON body once, a pending row per sink,
  one commit), then the runners' ``confirm`` of every event as a sink's delivery would;
* **memory**: the same ``Bus.publish`` with the spool in memory (``spool.path`` unset), the
  gateway without durability, to show what the file costs.

Each is run with ``synchronous=NORMAL`` (the default: survives kill -9, not a power cut) and
``FULL`` (an fsync per commit). Latency is per ``publish`` call (``perf_counter_ns``); the
"added p99" is the spool's p99 minus the memory spool's p99 in the same run.
"""

from __future__ import annotations

import argparse
import os
import platform
import sqlite3
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from gateway.c2.sinkrunner import SinkRunner
from gateway.config import RouteConfig, SinkEntry
from gateway.events import Detection, Event, Position, Sensor
from gateway.flow.bus import Bus
from gateway.ops.instruments import Instruments
from gateway.spool.store import Spool
from gateway.testing import NullSink

T0 = datetime(2026, 11, 23, 12, 0, tzinfo=UTC)


def make_events(n: int) -> list[Event]:
    """``n`` detections as the dialect makes them (distinct ids, realistic fields)."""
    return [
        Detection(
            event_id=f"F26E-001-det-{i}-{1_795_000_000_000_000 + i}",
            airframe="F26E-001",
            time=T0,
            sensor=Sensor.EO,
            object_class="tank",
            subtype="T-72",
            confidence=0.91,
            position=Position(lat_deg=58.41 + i * 1e-6, lon_deg=15.62, alt_msl_m=95.0),
            sigma_h_m=8.0,
        )
        for i in range(n)
    ]


def percentile(samples: list[int], q: float) -> float:
    ordered = sorted(samples)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] / 1000.0  # µs


def plain_sqlite(events: list[Event], path: Path, sync: str) -> tuple[float, list[int]]:
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute(f"PRAGMA synchronous={sync}")
    db.execute("CREATE TABLE events (seq INTEGER PRIMARY KEY, event_id TEXT, body BLOB)")
    latencies: list[int] = []
    start = time.perf_counter()
    for event in events:
        t0 = time.perf_counter_ns()
        body = event.model_dump_json().encode()
        db.execute("BEGIN")
        db.execute("INSERT INTO events (event_id, body) VALUES (?, ?)", (event.event_id, body))
        db.execute("COMMIT")
        latencies.append(time.perf_counter_ns() - t0)
    elapsed = time.perf_counter() - start
    db.close()
    return len(events) / elapsed, latencies


def through_bus(
    events: list[Event], spool: Spool, sinks: int
) -> tuple[float, list[int], Callable[[], None]]:
    inst = Instruments()
    names = [f"s{i}" for i in range(sinks)]
    runners = {
        name: SinkRunner(
            SinkEntry(name=name, type="null", queue_max=len(events) + 1),
            NullSink(name),
            inst,
            spool=spool,
        )
        for name in names
    }
    bus = Bus([RouteConfig(sinks=tuple(names))], runners, inst, spool=spool)
    latencies: list[int] = []
    start = time.perf_counter()
    for event in events:
        t0 = time.perf_counter_ns()
        bus.publish(event)
        latencies.append(time.perf_counter_ns() - t0)
    publish_s = time.perf_counter() - start

    def confirm_all() -> None:
        for runner in runners.values():
            items, _ = runner.outbox.take(len(events))
            for i in range(0, len(items), 100):  # a sink's batch at a time
                runner.outbox.confirm(items[i : i + 100])

    return len(events) / publish_s, latencies, confirm_all


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--events", type=int, default=20_000)
    parser.add_argument("--full-events", type=int, default=2_000, help="events with FULL sync")
    parser.add_argument("--sinks", type=int, default=2, help="durable sinks per event")
    args = parser.parse_args()
    rows = []
    for sync, n in (("NORMAL", args.events), ("FULL", args.full_events)):
        events = make_events(n)
        with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_DIR")) as tmp:
            plain_rate, plain_lat = plain_sqlite(events, Path(tmp) / "plain.db", sync)
            spool = Spool(Path(tmp) / "spool.db", sync=sync.lower())
            rate, lat, confirm_all = through_bus(events, spool, args.sinks)
            start = time.perf_counter()
            confirm_all()
            confirm_rate = n * args.sinks / (time.perf_counter() - start)
            spool.close()
        memory_rate, memory_lat, _ = through_bus(events, Spool(), args.sinks)
        rows.append(
            (sync, n, plain_rate, percentile(plain_lat, 0.99), rate, percentile(lat, 0.99),
             memory_rate, percentile(memory_lat, 0.99), confirm_rate)
        )  # fmt: skip
    print(
        f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, SQLite {sqlite3.sqlite_version}, "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {args.sinks} sinks per event\n"
    )
    print(
        "| sync | events | sqlite3 plain ev/s | p99 µs | spool ev/s | p99 µs | spool/plain "
        "| memory ev/s | p99 µs | added p99 µs | confirms/s |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for sync, n, pr, pp, sr, sp, mr, mp, cr in rows:
        print(
            f"| {sync} | {n:,} | {pr:,.0f} | {pp:,.0f} | {sr:,.0f} | {sp:,.0f} | {sr / pr:.2f} "
            f"| {mr:,.0f} | {mp:,.0f} | {sp - mp:,.0f} | {cr:,.0f} |"
        )


if __name__ == "__main__":
    main()
