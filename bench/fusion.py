"""Fusion benchmark: the tracker's throughput and latency as the live tracks grow.

Reproducible: ``python bench/fusion.py`` (``--help`` for options). Prints a Markdown table.

For each count in ``--tracks`` (10, 100, 1,000, 10,000 by default), a square theatre around
65.8° N 21.7° E holds that many moving targets (random positions, headings, speeds up to their
class's limit or 40 m/s, the dialect's classes). Its side is ``--area-km`` for 1,000 targets
and grows with √count, so the density (0.1 per km² by default) stays the same and the table
shows how the cost grows with the number of tracks alone; ``--fixed-area`` keeps the side
fixed instead (crowding as well: more tracks near each detection). Four airframes
report them round-robin so each target is seen about once a second (σ 8 m, Gaussian noise),
each detection its own sensor frame. Four rounds first create and confirm every track (M of
N); then ``--detections`` reports are timed through a fresh ``Tracker``:

* throughput: ``update`` as fast as possible over the whole stream (plus ``tick`` once per
  second of data time, as the processor does), detections per second of wall time;
* latency: a second pass timing each ``update`` call with ``time.perf_counter_ns``.

``--all-pairs`` also runs the all-pairs candidate scan (no spatial grid) for the counts up to
1,000 and asserts both end with the same tracks, so the comparison is like for like. Event
construction (pydantic) is part of the cost measured: ``update`` returns Track events.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import random
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

from gateway.events import Detection, Position, Sensor
from gateway.flow.localplane import displace
from tracking import DEFAULT_CLASSES, Tracker, TrackerSettings
from tracking.priors import load_priors

LAT0, LON0 = 65.8, 21.7
T0 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
AIRFRAMES = ("F26E-0001", "F26E-0002", "F26E-0003", "F26E-0004")


def make_stream(tracks: int, detections: int, area_km: float, seed: int) -> list[Detection]:
    """One creating detection per target, then ``detections`` round-robin reports."""
    rng = random.Random(seed)
    half = area_km * 500.0
    priors = load_priors()
    targets = []
    for _ in range(tracks):
        heading = rng.uniform(0.0, 2 * math.pi)
        cls = rng.choice(DEFAULT_CLASSES)
        speed = rng.uniform(0.0, min(40.0, priors[cls].max_speed_mps))
        targets.append(
            (
                rng.uniform(-half, half),
                rng.uniform(-half, half),
                speed * math.sin(heading),
                speed * math.cos(heading),
                cls,
            )
        )
    out: list[Detection] = []
    step_s = 1.0 / tracks  # each target about once a second
    for n in range(tracks + detections):
        t = n * step_s
        x0, y0, ve, vn, cls = targets[n % tracks]
        lat, lon = displace(
            LAT0, LON0, x0 + ve * t + rng.gauss(0.0, 8.0), y0 + vn * t + rng.gauss(0.0, 8.0)
        )
        out.append(
            Detection(
                event_id=f"d{n}",
                airframe=AIRFRAMES[(n // tracks + n) % len(AIRFRAMES)],
                time=T0 + timedelta(seconds=t),
                sensor=Sensor.EO,
                object_class=cls,
                confidence=rng.choice((0.6, 0.75, 0.8, 0.9)),
                position=Position(lat_deg=lat, lon_deg=lon, alt_msl_m=200.0),
                sigma_h_m=8.0,
            )
        )
    return out


def settings_for(index: str, warm: int) -> TrackerSettings:
    """The shipped defaults, the index asked for, and room for every target (warm = 4×)."""
    return TrackerSettings(index=index, max_tracks=max(5000, warm))  # type: ignore[arg-type]


def throughput(index: str, stream: list[Detection], warm: int) -> tuple[float, Tracker]:
    """Detections per second through ``update`` (and a tick per second of data time)."""
    tracker = Tracker(settings_for(index, warm))
    for detection in stream[:warm]:
        tracker.update(detection)
    rest = stream[warm:]
    next_tick = rest[0].time + timedelta(seconds=1)
    start = time.perf_counter()
    for detection in rest:
        tracker.update(detection)
        if detection.time >= next_tick:
            tracker.tick(detection.time)
            next_tick = detection.time + timedelta(seconds=1)
    elapsed = time.perf_counter() - start
    return len(rest) / elapsed, tracker


def latencies_us(index: str, stream: list[Detection], warm: int) -> list[float]:
    """Each ``update`` call's wall time (µs), sorted."""
    tracker = Tracker(settings_for(index, warm))
    for detection in stream[:warm]:
        tracker.update(detection)
    times: list[float] = []
    clock = time.perf_counter_ns
    for detection in stream[warm:]:
        begin = clock()
        tracker.update(detection)
        times.append((clock() - begin) / 1000.0)
    return sorted(times)


def quantile(values: list[float], q: float) -> float:
    return values[min(len(values) - 1, math.ceil(q * len(values)) - 1)]


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument(
        "--tracks", default="10,100,1000,10000", help="live target counts (10,100,1000,10000)"
    )
    parser.add_argument("--detections", type=int, default=20_000, help="reports timed (20000)")
    parser.add_argument(
        "--area-km", type=float, default=100.0, help="theatre side for 1,000 targets, km (100)"
    )
    parser.add_argument("--fixed-area", action="store_true", help="the same side for every count")
    parser.add_argument("--seed", type=int, default=1, help="random seed (1)")
    parser.add_argument("--all-pairs", action="store_true", help="also scan all pairs (<= 1000)")
    args = parser.parse_args()
    counts = [int(n) for n in args.tracks.split(",")]

    print(f"# fusion benchmark, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores (one used), "
          f"Python {platform.python_version()}, {platform.platform()}")  # fmt: skip
    print(
        f"\neach target seen about once a second by 4 airframes; {args.detections} detections "
        f"timed after 4 rounds of warm-up, seed {args.seed}\n"
    )
    print(
        "| live targets | theatre km | index | detections/s | µs/detection | p50 µs | p99 µs "
        "| p99.9 µs | live tracks | confirmed | merged |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for tracks in counts:
        side = args.area_km if args.fixed_area else args.area_km * math.sqrt(tracks / 1000)
        stream = make_stream(tracks, args.detections + 3 * tracks, side, args.seed)
        warm = 4 * tracks
        results = {}
        modes = ["grid"] + (["all_pairs"] if args.all_pairs and tracks <= 1000 else [])
        for index in modes:
            rate, tracker = throughput(index, stream, warm)
            lat = latencies_us(index, stream, warm)
            results[index] = tracker
            c = tracker.counts
            print(
                f"| {tracks:,} | {side:g} | {index} | {rate:,.0f} | {1e6 / rate:.1f} | "
                f"{quantile(lat, 0.5):.1f} | {quantile(lat, 0.99):.1f} | "
                f"{quantile(lat, 0.999):.1f} | {len(tracker)} | {len(tracker.confirmed_ids)} | "
                f"{c.merged} |",
                flush=True,
            )
        if len(results) == 2:
            assert results["grid"].track_ids == results["all_pairs"].track_ids
            assert results["grid"].counts == results["all_pairs"].counts


if __name__ == "__main__":
    main()
