"""Decode benchmark: the fast path (``gateway.fleet.fastdecode``) against pymavlink's parse.

Reproducible: ``python bench/decode.py`` (``--help`` for options). Prints a Markdown table.

The same frames, one datagram each, go through (1) a bare pymavlink ``parse_buffer`` loop
(one parser, as ``bench/ingest.py``'s peer) and (2) ``FastDecoder.decode``, falling back to
that pymavlink parser for a frame that is not one of the fast path's messages (what the
gateway would do). Both run in this process and are timed in CPU time
(``time.process_time``), one after the other, in 5 interleaved rounds; the table gives the
median ratio of frames/s (2)/(1) and its min and max. The frame sets:

- ``sim``: what ``bench/ingest.py`` sends: simulated airframes' telemetry (position 10 Hz,
  status 2 Hz, heartbeat 1 Hz), every frame one of the fast path's messages;
- ``sim+camera+detections``: the same with camera, gimbal and FISCHER_DETECTION frames;
- ``corpus``: every frame of every tlog in ../shared/corpus (real and SITL logs, MAVLink 1
  and 2, signed, corrupt): most are messages the gateway does not handle, which go to
  pymavlink either way; ``corpus, ours only`` keeps the frames of the fast path's messages.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.errors import Malformed
from gateway.fleet import mavlink as _registers_the_project_dialect  # noqa: F401
from gateway.fleet.fastdecode import FastDecoder, default_decoder
from gateway.fleet.tlog import read_tlog
from gateway.ops.logsetup import configure_logging
from gateway.sim.airframe import SimProfile, SimulatedAirframe

ROUNDS = 5
CORPUS = Path(__file__).resolve().parents[1].parent / "shared" / "corpus" / "mavlink"


def sim_frames(count: int, profile: SimProfile, airframes: int = 10) -> list[bytes]:
    """``count`` frames of ``airframes`` simulated airframes, interleaved in time order."""
    sims = [SimulatedAirframe(i + 1, profile, phase_rad=i) for i in range(airframes)]
    out: list[bytes] = []
    t = 0.0
    while len(out) < count:
        for sim in sims:
            out.extend(sim.frames_at(t))
        t += 0.05
    return out[:count]


def corpus_frames() -> list[bytes]:
    """Every frame of every tlog in the shared corpus (empty when it is absent)."""
    if not CORPUS.is_dir():
        return []
    return [record.frame for path in sorted(CORPUS.glob("*.tlog")) for record in read_tlog(path)]


def pymavlink_run(frames: list[bytes]) -> int:
    """pymavlink's parse of each frame; messages parsed (bad data included, as it returns)."""
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    parse = parser.parse_buffer
    count = 0
    for frame in frames:
        count += len(parse(frame) or ())
    return count


def fast_run(decoder: FastDecoder) -> Callable[[list[bytes]], int]:
    """The fast path over each frame, pymavlink for the frames it leaves."""

    def run(frames: list[bytes]) -> int:
        parser = mav.MAVLink(None)
        parser.robust_parsing = True
        parse = parser.parse_buffer
        decode = decoder.decode
        count = 0
        for frame in frames:
            try:
                msg = decode(frame)
            except Malformed:
                count += 1  # refused: counted as pymavlink counts its BAD_DATA
                continue
            count += 1 if msg is not None else len(parse(frame) or ())
        return count

    return run


def cpu_seconds(run: Callable[[list[bytes]], int], frames: list[bytes]) -> float:
    start = time.process_time()
    run(frames)
    return time.process_time() - start


def compare(frames: list[bytes], decoder: FastDecoder) -> tuple[float, float, list[float]]:
    """Median frames/s of pymavlink and of the fast path, and the ratio of each round."""
    fast = fast_run(decoder)
    theirs, ours, ratios = [], [], []
    for _ in range(ROUNDS):
        pm = cpu_seconds(pymavlink_run, frames)
        fp = cpu_seconds(fast, frames)
        theirs.append(len(frames) / pm)
        ours.append(len(frames) / fp)
        ratios.append(pm / fp)
    return statistics.median(theirs), statistics.median(ours), ratios


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=100_000, help="frames per simulated set")
    args = parser.parse_args()
    configure_logging("warning", sys.stderr)  # the damaged corpus log's warning, off stdout
    start = time.process_time()
    decoder = default_decoder()
    built_ms = (time.process_time() - start) * 1000
    if not decoder.messages:
        raise SystemExit("the fast path is off (see the fastdecode_disabled warning)")
    sets = {
        "sim": sim_frames(args.frames, SimProfile(gps_hz=0.0001)),
        "sim+camera+detections": sim_frames(
            args.frames, SimProfile(camera_hz=5.0, detection_hz=5.0)
        ),
    }
    corpus = corpus_frames()
    if corpus:
        sets["corpus"] = corpus
        ours = []
        for frame in corpus:
            try:
                if decoder.decode(frame) is not None:
                    ours.append(frame)
            except Malformed:
                continue
        sets["corpus, ours only"] = ours
    print(f"# decode benchmark, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}; CPU time, {ROUNDS} interleaved rounds; "
        f"decoders of {len(decoder.messages)} messages built from the XML in {built_ms:.0f} ms\n"
    )
    print("| frames | count | pymavlink frames/s | fast path frames/s | ratio median (min–max) |")
    print("| --- | --- | --- | --- | --- |")
    for name, frames in sets.items():
        theirs, ours_rate, ratios = compare(frames, decoder)
        print(
            f"| {name} | {len(frames):,} | {theirs:,.0f} | {ours_rate:,.0f} | "
            f"{statistics.median(ratios):.2f} ({min(ratios):.2f}–{max(ratios):.2f}) |"
        )
    if not corpus:
        print(f"\n(no corpus at {CORPUS}: the corpus rows are left out)")


if __name__ == "__main__":
    main()
