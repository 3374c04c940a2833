"""Ra 180 benchmark: what one track costs the sink, against the bare MGRS conversion.

Reproducible: ``python bench/ra180.py`` (``--help`` for options). Prints a Markdown table.

``--tracks`` hostile Track events at random positions around 65.8° N 21.7° E, moving, go
through the sink's ``Budget.offer`` (the CDM composed, fitted and encoded, the move check,
the held line) as fast as possible; the peer, in the same run, is the ``mgrs`` package
converting the same positions (``MGRS().toMGRS``), the step of a CDM no code of ours does.
Their ratio is the overhead of everything else (best of ``--rounds``, interleaved). The last
rows time ``next_due`` and ``sent`` (the head of the line, a heap) with ``--tracks``
messages held: the cost per message transmitted; and ``offer`` of new tracks to a budget
full at ``max_tracks`` with every track holding a message (each newcomer makes room:
the least important held message gives way, a second heap).
"""

from __future__ import annotations

import argparse
import os
import platform
import random
import time
from datetime import UTC, datetime
from pathlib import Path

import mgrs

from gateway.events import Position, Track
from sinks.ra180.budget import Budget
from sinks.ra180.cdm import Cdm, MessageType, compose

T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, else the platform's."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def make_tracks(count: int, seed: int) -> list[Track]:
    rng = random.Random(seed)
    return [
        Track(
            event_id=f"e{n}",
            track_id=f"T-{n}",
            time=T0,
            object_class=rng.choice(["tank", "armour", "loitering_munition"]),
            confidence=rng.uniform(0.5, 1.0),
            position=Position(
                lat_deg=65.8 + rng.uniform(-0.5, 0.5), lon_deg=21.7 + rng.uniform(-1, 1)
            ),
            cep50_m=5.0,
            cep90_m=9.0,
            speed_mps=rng.uniform(0, 40),
            course_deg=rng.uniform(0, 359.9),
            first_seen=T0,
            last_seen=T0,
            hostility="hostile",
        )
        for n in range(count)
    ]


def encode(track: Track, message_type: MessageType, number: int) -> tuple[Cdm, bytes]:
    cdm = compose(track, message_type=message_type, number=number)
    return cdm, " ".join(cdm.fields()).encode("ascii") + b"\r\n"


def budget(tracks: int) -> Budget:
    return Budget(
        encode,
        bytes_per_minute=1200,
        burst_bytes=260,
        min_move_m=100.0,
        max_tracks=tracks,
        report=frozenset({"hostile"}),
        now=0.0,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--tracks", type=int, default=10_000, help="tracks offered (and held)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--rounds", type=int, default=5, help="best of this many runs each")
    args = parser.parse_args()
    tracks = make_tracks(args.tracks, args.seed)

    converter = mgrs.MGRS()
    peer_s = ours_s = float("inf")
    for _ in range(args.rounds):  # interleaved, best of each: a shared machine is noisy
        started = time.perf_counter()
        for t in tracks:
            converter.toMGRS(t.position.lat_deg, t.position.lon_deg, MGRSPrecision=4)
        peer_s = min(peer_s, time.perf_counter() - started)
        b = budget(args.tracks)
        started = time.perf_counter()
        for t in tracks:
            b.offer(t)
        ours_s = min(ours_s, time.perf_counter() - started)
        assert b.held == args.tracks

    b.bucket.tokens = 1e12  # time the scan alone: every head affordable
    started = time.perf_counter()
    picks = 0
    while picks < 200 and (item := b.next_due(0.0)) is not None:
        b.sent(item, 0.0)
        picks += 1
    scan_s = (time.perf_counter() - started) / picks

    full = budget(args.tracks)
    for t in tracks:
        full.offer(t)
    newcomers = [t.model_copy(update={"track_id": f"N-{t.track_id}"}) for t in tracks]
    started = time.perf_counter()
    for t in newcomers:
        full.offer(t)
    full_s = (time.perf_counter() - started) / len(newcomers)
    assert full.held == args.tracks

    print(f"# Ra 180 benchmark, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    machine = f"{cpu_model()}, {os.cpu_count()} cores (one used)"
    print(f"machine: {machine}, Python {platform.python_version()}")
    print()
    print("| step | per track | tracks/s | ratio to mgrs |")
    print("| --- | --- | --- | --- |")
    n = args.tracks
    print(f"| mgrs `toMGRS` (peer) | {peer_s / n * 1e6:.1f} µs | {n / peer_s:,.0f} | 1.0 |")
    print(
        f"| `Budget.offer` (CDM + budget) | {ours_s / n * 1e6:.1f} µs | {n / ours_s:,.0f} | "
        f"{ours_s / peer_s:.1f} |"
    )
    print(f"| `next_due` + `sent` with {n:,} held | {scan_s * 1e6:.0f} µs | {1 / scan_s:,.0f} | |")
    row = f"| `offer` of a new track, {n:,} held (full) | {full_s * 1e6:.0f} µs"
    print(f"{row} | {1 / full_s:,.0f} | |")


if __name__ == "__main__":
    main()
