"""A guard on what ingest costs per frame, as a CPU-time ratio against bare pymavlink.

Absolute times mean nothing on a shared machine; the ratio of two loops timed in the same
process, interleaved, mostly does (both slow down together). ``Ingest.on_data`` (parse, sysid
demultiplexing, link bookkeeping, de-duplication, normalise, one Telemetry snapshot per frame
as below saturation, detections) is set against pymavlink's ``parse_buffer`` on the same
datagrams; and ingest of the same telemetry sealed in the tunnel (open, replay window, parse,
normalise, snapshots coalesced as under load) against pymavlink parsing it plain.
``bench/ingest.py`` and ``bench/e2e.py`` measure the real figures.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.config import AirframeConfig, LinkConfig
from gateway.events import Detection, Event, Telemetry
from gateway.fleet.dialect import fischer_detection
from gateway.fleet.ingest import Ingest, LinkIntake
from gateway.fleet.security.tunnel import DayKeys, Sealer, TunnelOpener
from gateway.ops.instruments import Instruments
from gateway.sim.airframe import SimProfile, SimulatedAirframe
from tests.gateway.fleet.test_ingest import T0

AIRFRAMES = 10
#: Ingest's frames/s ÷ pymavlink's, this test's loop on the 2-core development machine with
#: other work running (2026-11-27): medians 0.55-0.62 (0.44-0.48 before the snapshot was built
#: from one dict and the header fields read from the frame; 0.35-0.36 before events were built
#: without re-validation). Later the same day, under a load of 2 and side by side with the tree
#: before: 0.54-0.57 (0.48-0.53) once Position, Velocity and Attitude were checked by hand and
#: the snapshot built from a template. A clean-clone CI run beside two busy sessions measured
#: 0.43-0.47 (median 0.445): the floor leaves room for that load, not for a path a third slower.
FLOOR = 0.40
#: Tunnel ingest's frames/s ÷ plain pymavlink's, this test's loop, same machine and load
#: (2026-11-27): medians 0.74-0.75 side by side with the tree before (0.61-0.62) once the
#: small models were built per snapshot rather than validated per message and the open path
#: read its counters in one struct call (0.46-0.47 before the tunnel's header look-up, the
#: datagram path without lists and the header fields read from the frame). Same rule for the
#: floor.
TUNNEL_FLOOR = 0.52
#: Timed rounds of each test; the median is held to the floor.
ROUNDS = 5
#: Datagrams between two flushes in the tunnel test: telemetry coalesced as under load.
PER_PASS = 64


def datagrams() -> list[bytes]:
    """Telemetry of ten simulated airframes for 3 s and one detection per airframe a second."""
    sims = [SimulatedAirframe(i + 1, SimProfile(gps_hz=0.0001), phase_rad=i) for i in range(10)]
    packers = [mav.MAVLink(None, srcSystem=i + 1, srcComponent=1) for i in range(AIRFRAMES)]
    out: list[bytes] = []
    for step in range(60):
        t = step * 0.05
        for i, sim in enumerate(sims):
            out.extend(sim.frames_at(t))
            if step % 20 == i:
                msg = fischer_detection(
                    int(T0.timestamp() * 1e6) + step, step * 100 + i, 658_400_000, 217_000_000,
                    60.0, 8.0, 1, 1, 91, "T-72",
                )  # fmt: skip
                out.append(bytes(msg.pack(packers[i])))
    return out


def cpu(run: Callable[[], None]) -> float:
    start = time.process_time()
    run()
    return time.process_time() - start


def test_ingest_keeps_its_cpu_time_ratio_against_bare_pymavlink() -> None:
    frames = datagrams()
    events: list[Event] = []

    def ours() -> None:
        config = [
            AirframeConfig(
                id=f"AF-{s}",
                sysid=s,
                links=(LinkConfig(uri="udp://127.0.0.1:1", name="l", security="unsecured"),),
            )
            for s in range(1, AIRFRAMES + 1)
        ]
        ingest = Ingest(config, events.append, Instruments(), lambda: T0)
        ingest.register_link(LinkIntake("l", "unsecured", is_stream=False))
        on_data = ingest.on_data
        for frame in frames:
            on_data("l", "peer", frame)

    def theirs() -> None:
        parser = mav.MAVLink(None)
        parser.robust_parsing = True
        for frame in frames:
            parser.parse_buffer(frame)

    ours()  # warm: the fast decoder is built on first use, caches fill
    ratios = []
    for _ in range(ROUNDS):
        events.clear()
        mine = cpu(ours)
        ratios.append(cpu(theirs) / mine)
    assert sum(isinstance(e, Detection) for e in events) == 30
    ratios.sort()
    assert ratios[ROUNDS // 2] >= FLOOR, (
        f"ingest ÷ pymavlink CPU-time ratios {ratios}, floor {FLOOR}"
    )


def test_tunnel_ingest_keeps_its_cpu_time_ratio_against_plain_pymavlink() -> None:
    sims = [SimulatedAirframe(i + 1, SimProfile(gps_hz=0.0001), phase_rad=i) for i in range(10)]
    frames = [
        (i, frame)
        for step in range(80)
        for i, sim in enumerate(sims)
        for frame in sim.frames_at(step * 0.05)
    ]
    warm, timed = frames[: len(frames) // 4], frames[len(frames) // 4 :]
    keys = DayKeys(master=bytes(range(32)))
    config = [
        AirframeConfig(
            id=f"AF-{s}",
            sysid=s,
            links=(LinkConfig(uri="udp://127.0.0.1:1", name="l", security="tunnel"),),
        )
        for s in range(1, AIRFRAMES + 1)
    ]
    events: list[Event] = []

    def sealed(part: list[tuple[int, bytes]]) -> list[bytes]:
        # Every run seals afresh: a frame opened once is a replay to the next opener.
        sealers = [Sealer(f"AF-{i + 1}", keys, lambda: T0) for i in range(AIRFRAMES)]
        return [sealers[i].seal(frame) for i, frame in part]

    def ours() -> float:
        opener = TunnelOpener(keys, frozenset(c.id for c in config), lambda: T0)
        ingest = Ingest(config, events.append, Instruments(), lambda: T0, opener=opener)
        ingest.register_link(LinkIntake("l", "tunnel", is_stream=False))
        on_data = ingest.on_data

        async def feed(datagrams: list[bytes]) -> float:
            start = time.process_time()
            for n, data in enumerate(datagrams):
                on_data("l", "peer", data)
                if n % PER_PASS == PER_PASS - 1:
                    await asyncio.sleep(0)  # a loop pass: the snapshots of the pass are published
            await asyncio.sleep(0)
            return time.process_time() - start

        async def run() -> float:
            await feed(sealed(warm))  # the decoder is built on first use, caches fill
            return await feed(sealed(timed))

        return asyncio.run(run())

    def theirs() -> None:
        parser = mav.MAVLink(None)
        parser.robust_parsing = True
        for _, frame in timed:
            parser.parse_buffer(frame)

    ours()
    ratios = []
    for _ in range(ROUNDS):
        events.clear()
        mine = ours()
        ratios.append(cpu(theirs) / mine)
    # One snapshot per airframe and loop pass (warm-up and timed), whatever the frames of the pass.
    passes = len(warm) // PER_PASS + len(timed) // PER_PASS + 4
    assert 0 < sum(isinstance(e, Telemetry) for e in events) <= AIRFRAMES * passes
    ratios.sort()
    assert ratios[ROUNDS // 2] >= TUNNEL_FLOOR, (
        f"tunnel ingest ÷ plain pymavlink CPU-time ratios {ratios}, floor {TUNNEL_FLOOR}"
    )
