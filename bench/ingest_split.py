"""Where a message's CPU time goes in ingest with the tunnel on, against bare pymavlink.

Reproducible: ``python bench/ingest_split.py`` (``--airframes 1,100,250``, ``--rounds 3``).
On the datagrams of ``bench/ingest.py``'s part A (N airframes x its message mix, sealed in
the tunnel), each stage is timed with ``time.process_time`` in one process, so a shared
machine's load mostly cancels out of the ratios; median of the rounds. Prints a Markdown
table of CPU microseconds per message:

- pymavlink: a bare ``parse_buffer`` loop on the plain frames (the ratios' denominator);
- floor: the tunnel's ``open_frame`` and the fast decoder alone, per datagram. Nothing in
  ingest can cost less, so pymavlink ÷ floor bounds what the pipeline's ratio can reach;
- ingest: ``Ingest.on_data`` with a loop pass every 256 datagrams, the snapshots of each
  pass made but published nowhere (link bookkeeping, de-duplication, normalise, snapshots);
- pipeline: ``bench/ingest.py``'s ``gateway_pipeline``, through the bus to five null sinks.

The difference between the columns is what each layer adds: ingest - floor is the
bookkeeping, normalising and the snapshots; pipeline - ingest is the bus and the sinks.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from unittest import mock

import anyio
import anyio.lowlevel
import ingest  # bench/ingest.py, beside this file
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.app import Gateway
from gateway.fleet.fastdecode import default_decoder
from gateway.fleet.ingest import LinkIntake
from gateway.fleet.security.tunnel import DayKeys, TunnelOpener
from gateway.ops.logsetup import configure_logging
from gateway.testing import NullSink

STAGES = ("pymavlink", "floor", "ingest", "pipeline")


def split(airframes: int, key: str, rounds: int) -> dict[str, float]:
    """CPU microseconds per message of each stage (module docstring), median of ``rounds``."""
    seconds = max(1.0, 40_000 / (airframes * 13))
    plain = ingest.make_datagrams(airframes, seconds, False)
    sealed = ingest.make_datagrams(airframes, seconds, True)
    decode = default_decoder().decode

    def bare() -> None:
        parser = mav.MAVLink(None)
        parser.robust_parsing = True
        for data in plain:
            parser.parse_buffer(data)

    def floor() -> None:
        opener = TunnelOpener(
            DayKeys(master=ingest.MASTER),
            frozenset(ingest.airframe_id(i) for i in range(250)),
            lambda: datetime.now(UTC),
            freshness_s=3600,
        )
        opener.started_ms = 0  # sealed before it existed: see ingest.bare_pymavlink
        now_ms = time.time_ns() // 1_000_000
        for data in sealed:
            decode(opener.open_frame(data, "b", now_ms).payload)

    def ingest_only() -> float:
        sinks = {f"null{n}": NullSink(f"null{n}") for n in range(ingest.SINKS)}
        gateway = Gateway(ingest.config(airframes, True, 0, key), sinks=dict(sinks))
        opener = gateway.fleet.security.opener
        assert opener is not None
        opener.freshness_s, opener.started_ms = 3600, 0
        fleet_ingest = gateway.fleet.ingest
        fleet_ingest.register_link(LinkIntake("bench", "tunnel", is_stream=False))
        fleet_ingest._publish = lambda _event: True  # snapshots are made, published nowhere
        on_data = fleet_ingest.on_data

        async def run() -> float:
            start = time.process_time()
            for index, data in enumerate(sealed):
                on_data("bench", "peer", data)
                if index % 256 == 0:
                    await anyio.lowlevel.checkpoint()  # a loop pass: its snapshots are made
            await anyio.lowlevel.checkpoint()
            return time.process_time() - start

        return anyio.run(run, backend_options={"use_uvloop": True})

    def cpu(run: Callable[[], None]) -> float:
        start = time.process_time()
        run()
        return time.process_time() - start

    def pipeline() -> float:
        # gateway_pipeline times itself with perf_counter: CPU time here instead.
        with mock.patch.object(ingest.time, "perf_counter", time.process_time):
            rate = ingest.gateway_pipeline(sealed, airframes, True, key)
        return len(sealed) / rate

    times: dict[str, list[float]] = {stage: [] for stage in STAGES}
    for _ in range(rounds):
        times["pymavlink"].append(cpu(bare))
        times["floor"].append(cpu(floor))
        times["ingest"].append(ingest_only())
        times["pipeline"].append(pipeline())
    return {stage: 1e6 * statistics.median(t) / len(plain) for stage, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--airframes", default="1,100,250", help="at most 250: 8-bit sysids")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    configure_logging("warning", sys.stderr)
    key = Path(tempfile.mkdtemp()) / "master.key"
    key.write_text(ingest.MASTER.hex())
    key.chmod(0o600)
    print(f"# where ingest's CPU time goes, tunnel on, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC\n")
    print(
        "| airframes | pymavlink µs/msg | floor: open + fast decode | pymavlink ÷ floor "
        "| ingest, snapshots unpublished | pipeline, 5 null sinks | pymavlink ÷ pipeline |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for n in (int(x) for x in args.airframes.split(",")):
        us = split(n, str(key), args.rounds)
        print(
            f"| {n} | {us['pymavlink']:.2f} | {us['floor']:.2f} "
            f"| {us['pymavlink'] / us['floor']:.2f} | {us['ingest']:.2f} "
            f"| {us['pipeline']:.2f} | {us['pymavlink'] / us['pipeline']:.2f} |"
        )


if __name__ == "__main__":
    main()
