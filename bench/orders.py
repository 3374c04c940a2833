"""Orders benchmark: how long the acceptance checks of one order hold the event loop.

Reproducible: ``python bench/orders.py`` (``--help`` for options). Prints a Markdown table.

The orders processor checks an order synchronously, on the event loop ingest shares, so its
cost is a pause of ingest. Measured, in the same run, for an observe-point order and for an
area order of ``--corners`` corners (radius about 30 km) over a flat SRTM tile made here:

* **checks**: ``processors._orderplan.plan`` (for the area, its lawnmower: 162 lines 400 m
  above the tile's ground, ``max_survey_lines`` at its ceiling) then ``check`` (geofence,
  terrain floor along every leg every 250 m, endurance with the return leg), as the
  processor runs them;
* **geofence**: ``gateway.domain.mission.route_exit`` alone on the route the check gives it
  (every point in the ellipsoidal gnomonic plane, each leg as geodesic and rhumb line);
* **geodesic peer**: the same terrain samples placed along the geodesic with geographiclib
  (``Geodesic.WGS84.Direct`` per sample) and looked up in the same DEM: what the terrain check
  would cost sampling on the geodesic instead of interpolating.

Per order: the median and p99 over ``--runs`` runs, and the peer's median over ours.
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import tempfile
import time
from datetime import UTC, datetime
from itertools import pairwise
from pathlib import Path

import numpy as np
from geographiclib.geodesic import Geodesic  # type: ignore[import-untyped]

from gateway.domain.mission import route_exit
from gateway.domain.terrain import DemSource, TerrainModel
from gateway.events import FiveLineOrder, OrderArea, OrderTask, Position, Telemetry
from processors._orderplan import Limits, Plan, _samples, check, plan

NOW = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)
LIMITS = Limits(
    25.0,
    10.0,
    600.0,
    300.0,
    0.0,
    0.5,
    ((65.0, 20.0), (65.0, 23.0), (66.5, 23.0), (66.5, 20.0)),
    max_survey_lines=1000,  # the option's ceiling: the area's survey is 162 lines
)


def orders(corners: int) -> dict[str, FiveLineOrder]:
    ring = tuple(
        Position(
            lat_deg=65.5 + 0.27 * math.sin(2 * math.pi * i / corners),
            lon_deg=21.5 + 0.65 * math.cos(2 * math.pi * i / corners),
        )
        for i in range(corners)
    )
    common = {"event_id": "b", "order_id": "b", "source": "bench", "time": NOW}
    return {
        "observe point": FiveLineOrder(
            **common,
            task=OrderTask.OBSERVE_POINT,
            location=OrderArea(point=Position(lat_deg=65.6, lon_deg=21.6)),
        ),
        f"area, {corners} corners": FiveLineOrder(
            **common, task=OrderTask.RECON_AREA, location=OrderArea(polygon=ring)
        ),
    }


def geodesic_peer(chosen: Plan, terrain: TerrainModel) -> None:
    points = (chosen.route[0], *chosen.task_points)
    for a, b in pairwise(points):
        line = Geodesic.WGS84.InverseLine(a[0], a[1], b[0], b[1])
        steps = max(1, math.ceil(line.s13 / 250.0))
        for i in range(steps + 1):
            at = line.Position(line.s13 * i / steps)
            terrain.lookup(at["lat2"], at["lon2"])


def timed(call, runs: int) -> list[float]:  # type: ignore[no-untyped-def]
    call()
    out = []
    for _ in range(runs):
        start = time.perf_counter_ns()
        call()
        out.append((time.perf_counter_ns() - start) / 1e6)
    return sorted(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--corners", type=int, default=64)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        grid = np.full((1201, 1201), 100, dtype=">i2")
        (Path(tmp) / "N65E021.hgt").write_bytes(grid.tobytes())
        terrain = TerrainModel([DemSource("srtm", Path(tmp), "hgt", 5.0)])
        here = Telemetry(
            event_id="t",
            airframe="A",
            time=NOW,
            position=Position(lat_deg=65.5, lon_deg=21.5, alt_msl_m=500.0),
            endurance_remaining_min=600.0,
        )
        machine = platform.processor() or platform.machine()
        print(
            f"Machine: {machine}, Python {platform.python_version()}, {datetime.now(UTC):%Y-%m-%d}"
        )
        print()
        head = ["order", "samples", "checks median ms", "checks p99 ms"]
        head += ["geofence median ms", "geodesic peer median ms", "peer / checks"]
        print(f"| {' | '.join(head)} |")
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
        for name, order in orders(args.corners).items():
            chosen = plan(order, here, None, LIMITS, terrain)
            assert isinstance(chosen, Plan)

            def ours_once(o: FiveLineOrder = order) -> None:
                check(plan(o, here, None, LIMITS, terrain), here, terrain, LIMITS)  # type: ignore[arg-type]

            ours = timed(ours_once, args.runs)
            route = (chosen.route[0], *chosen.task_points, chosen.route[-1])
            fence = LIMITS.fence
            assert fence is not None
            geofence = timed(lambda r=route, f=fence: route_exit(f, r), args.runs)
            peer = timed(lambda c=chosen: geodesic_peer(c, terrain), args.runs)
            samples = len(_samples((chosen.route[0], *chosen.task_points)))
            ours_ms, peer_ms = statistics.median(ours), statistics.median(peer)
            p99 = ours[min(len(ours) - 1, int(len(ours) * 0.99))]
            cells = [name, str(samples), f"{ours_ms:.2f}", f"{p99:.2f}"]
            cells += [f"{statistics.median(geofence):.2f}", f"{peer_ms:.2f}"]
            print(f"| {' | '.join(cells)} | {peer_ms / ours_ms:.1f}× |")


if __name__ == "__main__":
    main()
