"""Time-slider benchmark: the picture at an instant from a large JSONL archive (docs/map.md §6).

Reproducible: ``python bench/map_replay.py`` (``--help`` for options). Prints a Markdown table.

Writes, in a temporary folder, the archive a node keeps of ``--tracks`` tracks and
``--airframes`` airframes each updated once a second for ``--seconds`` (the events of
bench/map_load.py, one JSON line each as the ``jsonl`` sink writes them), then asks for the
picture at instants in it with the map sink's default budget, as ``GET /api/picture?at=`` does,
and reports the time taken, the bytes read, whether the budget cut the window and how many of
the entities the picture holds.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

from map_load import world  # bench/ is the script's folder: its neighbour

from sinks.map.archive import ArchiveBudget, replay
from sinks.map.config import MapSinkConfig
from sinks.map.picture import Limits


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tracks", type=int, default=1000)
    parser.add_argument("--airframes", type=int, default=250)
    parser.add_argument("--seconds", type=int, default=300, help="archive length (s)")
    args = parser.parse_args()

    config = MapSinkConfig()
    limits = Limits(expire_after_s=config.expire_after_s)
    budget = ArchiveBudget(
        max_bytes=config.replay_max_mb * 1024 * 1024, max_seconds=config.replay_max_s
    )
    tick = world(args.tracks, args.airframes)
    start = datetime(2026, 11, 27, 6, 0, tzinfo=UTC)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        live = Path(folder) / "archive.jsonl"
        with live.open("wb") as out:
            for n in range(args.seconds * 10):
                when = start + timedelta(seconds=n / 10)
                out.write(b"".join(e.model_dump_json().encode() + b"\n" for e in tick(n, when)))
        size = live.stat().st_size
        for fraction in (0.1, 0.5, 1.0):
            at = start + timedelta(seconds=args.seconds * fraction)
            began = time.perf_counter()
            done = replay(live, at, limits, budget)
            took = time.perf_counter() - began
            sizes = done.picture.sizes()
            rows.append((at, took, done, sizes["track"], sizes["airframe"]))

    print(f"map replay benchmark, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {platform.node()}")
    print(
        f"archive: {args.tracks} tracks and {args.airframes} airframes at 1 update/s for "
        f"{args.seconds} s: {size / 1e6:.0f} MB; budget {config.replay_max_mb} MiB, "
        f"{config.replay_max_s:g} s"
    )
    print()
    print("| at | time | read | events kept | tracks | airframes | truncated |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for at, took, done, tracks, airframes in rows:
        print(
            f"| +{(at - start).total_seconds():.0f} s | {took:.2f} s | "
            f"{done.bytes_read / 1e6:.1f} MB | {done.events} | {tracks} | {airframes} | "
            f"{'yes' if done.truncated else 'no'} |"
        )


if __name__ == "__main__":
    main()
