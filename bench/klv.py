"""KLV benchmark: ST 0601 packets encoded and decoded per second, ours against stanag4609.

Reproducible: ``python bench/klv.py`` (``--help`` for options). Prints Markdown tables.

The same ``--packets`` VideoFrameMetadata events (the seed example's values, moving) are
turned into ST 0601 packets, in the same run, by:

* **ours**: ``sinks.klv.uas.frame_packet`` (event → tags → bytes), what the klv
  sink does per event;
* **stanag4609**: ``stanag4609.st0601.encode_uas_local_set`` (0.4.0, pure Python) from the
  same ``{tag: value}`` dictionary (built beforehand, so it is not charged for the mapping).

and decoded by ``sinks.klv.st0601.decode``, ``stanag4609.st0601.decode_uas_local_set``
and ``klvdata.StreamParser`` (0.0.3). Each is the best of ``--repeat`` runs. The last line is
the share of one core that ``--airframes`` airframes at ``--rate`` metadata packets a second
would take to encode with ours.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import Any

from gateway.events import Position, VideoFrameMetadata
from sinks.klv.st0601 import Value, decode
from sinks.klv.uas import frame_packet, frame_values

T0 = datetime(2026, 11, 22, 10, 15, 30, 250000, tzinfo=UTC)


def make_events(n: int) -> list[VideoFrameMetadata]:
    """``n`` frames of one airframe's camera at 30 Hz, the seed example's values drifting."""
    return [
        VideoFrameMetadata(
            event_id=f"F26E-001-vfm-{i}",
            airframe="F26E-001",
            time=T0 + timedelta(microseconds=33_333 * i),
            sensor_position=Position(
                lat_deg=58.410812 + i * 1e-7, lon_deg=15.621403, alt_msl_m=612.4, alt_hae_m=640.0
            ),
            heading_deg=87.5,
            pitch_deg=-2.5,
            roll_deg=3.0,
            airspeed_mps=24.0,
            groundspeed_mps=23.0,
            alt_agl_m=520.0,
            hfov_deg=12.5,
            vfov_deg=7.0,
            sensor_azimuth_deg=45.0,
            sensor_elevation_deg=-30.0,
            sensor_roll_deg=0.0,
            frame_centre=Position(lat_deg=58.423917, lon_deg=15.650112, alt_msl_m=92.65),
            frame_centre_source="camera",
            slant_range_m=1250.0,
            target_width_m=274.0,
        )
        for i in range(n)
    ]


def best_rate(run: Callable[[], Any], n: int, repeat: int) -> float:
    """Items per second of the fastest of ``repeat`` runs of ``run`` over ``n`` items."""
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - start)
    return n / best


def stanag_values(values: dict[int, Value]) -> dict[int, Any]:
    """Our tag values as stanag4609 takes them (IMAPB tags need their wire length)."""
    from stanag4609.st0601 import IMAPFieldValue

    return {t: IMAPFieldValue(v, 3) if t == 113 else v for t, v in values.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--packets", type=int, default=3000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--airframes", type=int, default=50)
    parser.add_argument("--rate", type=float, default=30.0, help="packets/s per airframe")
    args = parser.parse_args()
    n = args.packets
    events = make_events(n)
    packets = [frame_packet(e) for e in events]
    rows: list[tuple[str, str, float]] = []
    ours_encode = best_rate(lambda: [frame_packet(e) for e in events], n, args.repeat)
    rows.append(("encode", "ours (event → packet)", ours_encode))
    rows.append(("decode", "ours", best_rate(lambda: [decode(p) for p in packets], n, args.repeat)))
    try:
        from stanag4609.st0601 import decode_uas_local_set, encode_uas_local_set

        values = [stanag_values(frame_values(e)) for e in events]
        rate = best_rate(lambda: [encode_uas_local_set(v) for v in values], n, args.repeat)
        rows.append(("encode", "stanag4609 0.4.0 (tags → packet)", rate))
        rate = best_rate(lambda: [decode_uas_local_set(p) for p in packets], n, args.repeat)
        rows.append(("decode", "stanag4609 0.4.0 (strict)", rate))
    except ImportError:
        print("stanag4609 not installed: its rows are missing")
    try:
        import klvdata

        stream = b"".join(packets)
        rate = best_rate(lambda: list(klvdata.StreamParser(stream)), n, args.repeat)
        rows.append(("decode", "klvdata 0.0.3", rate))
    except ImportError:
        print("klvdata not installed: its row is missing")
    cpu = platform.processor() or platform.machine()
    print(f"{n} packets of {len(packets[0])} bytes, best of {args.repeat}; Python "
          f"{platform.python_version()}, {cpu}, {os.cpu_count()} CPUs")  # fmt: skip
    print()
    print("| direction | codec | packets/s | ratio to ours |")
    print("|---|---|---:|---:|")
    for direction, name, rate in rows:
        ours = ours_encode if direction == "encode" else rows[1][2]
        print(f"| {direction} | {name} | {rate:,.0f} | {rate / ours:.2f} |")
    load = args.airframes * args.rate
    print()
    print(f"{args.airframes} airframes × {args.rate:g} packets/s = {load:,.0f} packets/s: "
          f"{100 * load / ours_encode:.1f} % of one core to encode (ours)")  # fmt: skip


if __name__ == "__main__":
    main()
