"""Map benchmark: 1,000 live tracks and 250 airframes at 1 update/s each (docs/map.md).

Reproducible: ``python bench/map_load.py`` (``--help`` for options). Prints a Markdown table.

The map sink runs in this process, in an event loop of its own thread, fed by a generator of
``--tracks`` tracks and ``--airframes`` airframes, each updated once a second (in batches every
100 ms, as the sink runner would deliver them). Three phases of ``--seconds`` each:

A. no client: the process's CPU for the picture alone (and the generator);
B. one SSE client reading the stream (a plain HTTP client in a thread): the extra CPU the
   stream costs the node, in % of one core (B - A);
C. Debian's headless Chromium showing the page (``--no-browser`` leaves it out): the node's
   extra CPU again, and the browser's frame intervals (``requestAnimationFrame``): p50, p95
   and max, and whether the page kept up with the stream (its ``seq`` against the node's).
"""

from __future__ import annotations

import argparse
import http.client
import math
import platform
import shutil
import statistics
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import Any

import anyio
import anyio.abc
from anyio.from_thread import start_blocking_portal

from gateway.events import Event, Position, Telemetry, Track
from sinks.map import MapSink, MapSinkConfig

CENTRE = (65.84, 21.66)
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def world(tracks: int, airframes: int) -> Callable[[int, datetime], list[Event]]:
    """Events of tick ``n`` (10 a second): a tenth of every entity moves."""

    def tick(n: int, now: datetime) -> list[Event]:
        events: list[Event] = []
        seconds = n / 10
        for i in range(n % 10, tracks, 10):
            angle = (i * 137.5 + seconds * 2) % 360
            radius = 0.05 + (i % 50) * 0.002
            lat = CENTRE[0] + radius * math.sin(math.radians(angle))
            lon = CENTRE[1] + 2 * radius * math.cos(math.radians(angle))
            events.append(
                Track(
                    event_id=f"t{i}-{n}",
                    track_id=f"T{i}",
                    time=now,
                    object_class="loitering_munition" if i % 3 else "tank",
                    confidence=0.9,
                    position=Position(lat_deg=lat, lon_deg=lon),
                    cep50_m=20.0,
                    cep90_m=40.0,
                    speed_mps=30.0,
                    course_deg=(angle + 90) % 360,
                    first_seen=now - timedelta(seconds=seconds),
                    last_seen=now,
                    hostility="hostile",
                    sidc="SHAPMFQ--------" if i % 3 else "SHGPUCA--------",
                )
            )
        for i in range(n % 10, airframes, 10):
            angle = (i * 97.0 + seconds * 3) % 360
            events.append(
                Telemetry(
                    event_id=f"a{i}-{n}",
                    airframe=f"F26E-{i:03d}",
                    time=now,
                    position=Position(
                        lat_deg=CENTRE[0] + 0.08 * math.sin(math.radians(angle)),
                        lon_deg=CENTRE[1] + 0.16 * math.cos(math.radians(angle)),
                        alt_msl_m=600.0,
                    ),
                    heading_deg=(angle + 90) % 360,
                    groundspeed_mps=25.0,
                    battery_pct=80.0,
                    endurance_remaining_min=90.0,
                    active_link="fleet",
                )
            )
        return events

    return tick


class Feeder:
    """Drives the sink from its own event loop: 10 batches a second."""

    def __init__(self, sink: MapSink, tick: Callable[[int, datetime], list[Event]]) -> None:
        self.sink = sink
        self.tick = tick
        self.sent = 0
        self.late = 0

    async def run(self, *, task_status: anyio.abc.TaskStatus[None]) -> None:
        task_status.started()
        start = time.monotonic()
        n = 0
        while True:
            batch = self.tick(n, datetime.now(UTC))
            await self.sink.send(batch)
            self.sent += len(batch)
            n += 1
            delay = start + n / 10 - time.monotonic()
            if delay < 0:
                self.late += 1
            await anyio.sleep(max(delay, 0))


def cpu_percent(seconds: float) -> float:
    before_cpu, before = time.process_time(), time.monotonic()
    time.sleep(seconds)
    return 100 * (time.process_time() - before_cpu) / (time.monotonic() - before)


def read_stream(url: str, stop: threading.Event, counts: dict[str, int]) -> None:
    host, port = url.split("//")[1].rstrip("/").rsplit(":", 1)
    conn = http.client.HTTPConnection(host, int(port), timeout=30)
    conn.request("GET", "/api/stream")
    response = conn.getresponse()
    while not stop.is_set():
        line = response.readline()
        if not line:
            break
        if line.startswith(b"data: "):
            counts["messages"] += 1
    conn.close()


def browse(url: str, seconds: float, node_seq: Callable[[], int]) -> dict[str, Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=shutil.which("chromium"), headless=True, args=FLAGS
        )
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(url)
            page.wait_for_function("() => window.fgMap && window.fgMap.state.snapshots >= 1")
            page.wait_for_function("() => window.fgMap.symbols() > 0")
            page.evaluate(
                """() => { window.fgFrames = []; let last = performance.now();
                  const step = (t) => { window.fgFrames.push(t - last); last = t;
                    requestAnimationFrame(step); };
                  requestAnimationFrame(step); }"""
            )
            cpu = cpu_percent(seconds)
            frames = page.evaluate("() => window.fgFrames.slice(1)")
            page_seq = page.evaluate("() => window.fgMap.state.seq")
            behind = node_seq() - page_seq
            symbols = page.evaluate("() => window.fgMap.symbols()")
        finally:
            browser.close()
    frames.sort()
    return {
        "cpu": cpu,
        "frames": len(frames),
        "p50": statistics.median(frames) if frames else math.nan,
        "p95": frames[int(0.95 * (len(frames) - 1))] if frames else math.nan,
        "max": frames[-1] if frames else math.nan,
        "behind": behind,
        "symbols": symbols,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tracks", type=int, default=1000)
    parser.add_argument("--airframes", type=int, default=250)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--no-browser", action="store_true")
    args = parser.parse_args()

    sink = MapSink("map", MapSinkConfig(port=0, max_connections=8))
    feeder = Feeder(sink, world(args.tracks, args.airframes))
    with start_blocking_portal() as portal:
        portal.call(sink.open)
        assert sink.url is not None
        portal.start_task(sink.run)
        portal.start_task(feeder.run)
        time.sleep(2.0)  # every entity once
        idle = cpu_percent(args.seconds)

        stop = threading.Event()
        counts = {"messages": 0}
        reader = threading.Thread(target=read_stream, args=(sink.url, stop, counts), daemon=True)
        reader.start()
        time.sleep(1.0)
        first = counts["messages"]
        streaming = cpu_percent(args.seconds)
        rate = (counts["messages"] - first) / args.seconds
        stop.set()

        browsed = None
        if not args.no_browser and shutil.which("chromium"):
            browsed = browse(sink.url, args.seconds, lambda: sink.hub.seq)
        portal.call(sink.aclose)
        portal.call(portal.stop, True)

    print(f"map benchmark, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {platform.node()}")
    print(
        f"{args.tracks} tracks and {args.airframes} airframes at 1 update/s each "
        f"({args.tracks + args.airframes} events/s); {args.seconds:g} s per phase; "
        f"late batches {feeder.late}"
    )
    print()
    print("| phase | node CPU (% of one core) | stream's share | other |")
    print("| --- | --- | --- | --- |")
    print(f"| A. no client | {idle:.1f} | | |")
    print(f"| B. one SSE client | {streaming:.1f} | {streaming - idle:+.1f} | {rate:.0f} msg/s |")
    if browsed is not None:
        print(
            f"| C. Chromium on the page | {browsed['cpu']:.1f} | {browsed['cpu'] - idle:+.1f} | "
            f"frames p50 {browsed['p50']:.0f} ms, p95 {browsed['p95']:.0f} ms, max "
            f"{browsed['max']:.0f} ms over {browsed['frames']} frames; {browsed['symbols']} "
            f"symbols; page {browsed['behind']} changes behind at the end |"
        )


if __name__ == "__main__":
    main()
