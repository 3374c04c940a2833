"""Hop-event intake benchmark: a flood of FISCHER_HOP_EVENTs through the gateway's ingest
against a bare pymavlink parse loop.

Reproducible: ``python bench/hop_events.py`` (``--help`` for options). Prints a Markdown table.

The same datagrams (one FISCHER_HOP_EVENT each, every fourth a jam-triggered hop, hop counts
rising) go, in the same run, through (1) a bare pymavlink ``parse_buffer`` loop, the peer, and
(2) ``Ingest.on_data`` of a gateway with a memory sink routed ``hop``: parsing, attribution,
the hop handler's counters and its per-airframe rate cap, and ``Bus.publish`` of what passes
the cap. The ratio is (2)/(1) in messages per second. The table also shows how many events
were published (the cap lets a few through) and the traced memory still allocated after the
flood (it must not grow with the number of frames).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
import tracemalloc
from datetime import UTC, datetime

import anyio
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.app import Gateway
from gateway.config import Config
from gateway.fleet.hopdialect import FischerHopEvent
from gateway.testing import MemorySink


def datagrams(n: int) -> list[bytes]:
    """``n`` hop reports of airframe 1, as the airframe would send them."""
    encoder = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    now_us = int(time.time() * 1e6)
    out = []
    for i in range(n):
        jammed = i % 4 == 3
        msg = FischerHopEvent(
            now_us + i * 500_000, 2_405_000_000 + (i % 4) * 25_000_000, 0x5D0B1C2A,
            (i + 1) * 41_000 % 2**32, i % 4, 1 if jammed else 0, -60, -27 if jammed else 127,
        )  # fmt: skip
        out.append(bytes(msg.pack(encoder)))
        encoder.seq = (encoder.seq + 1) % 256
    return out


def bare(frames: list[bytes]) -> float:
    """Messages per second of pymavlink alone, one datagram at a time."""
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    start = time.perf_counter()
    for frame in frames:
        parser.parse_buffer(frame)
    return len(frames) / (time.perf_counter() - start)


async def gateway(frames: list[bytes]) -> tuple[float, int, int]:
    """Messages per second through ingest, events published, bytes still traced after it."""
    config = Config.model_validate(
        {
            "health": {"enabled": False},
            "airframes": [
                {
                    "id": "F26E-001",
                    "sysid": 1,
                    "links": [{"uri": "udp://127.0.0.1:0", "security": "unsecured"}],
                }
            ],
            "sinks": [{"name": "mem", "type": "memory"}],
            "routes": [{"sinks": ["mem"], "kinds": ["hop"]}],
        }
    )
    gw = Gateway(config, sinks={"mem": MemorySink("mem")})
    link = next(iter(gw.fleet.links.values())).label
    peer = ("127.0.0.1", 14550)
    published = gw.instruments.events.labels("hop")
    half = len(frames) // 2
    start = time.perf_counter()
    for frame in frames[:half]:  # timed without tracing, which slows every allocation
        gw.fleet.ingest.on_data(link, peer, frame)
    elapsed = time.perf_counter() - start
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for frame in frames[half:]:  # a second flood as long: what it leaves allocated
        gw.fleet.ingest.on_data(link, peer, frame)
    grown = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    return half / elapsed, int(published.value), grown


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=200_000, help="datagrams per run")
    args = parser.parse_args()
    frames = datagrams(args.frames)
    peer_rate = bare(frames)
    ours, published, grown = anyio.run(gateway, frames)
    print(f"# hop-event intake benchmark, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}; {args.frames:,} datagrams\n"
    )
    print("| run | messages/s | ratio to pymavlink | events published | memory after flood |")
    print("| --- | --- | --- | --- | --- |")
    print(f"| pymavlink parse_buffer | {peer_rate:,.0f} | 1.00 | - | - |")
    print(
        f"| gateway ingest (hop) | {ours:,.0f} | {ours / peer_rate:.2f} | {published:,} "
        f"| {grown / 1024:+.1f} KiB |"
    )


if __name__ == "__main__":
    main()
