"""Tracking benchmark: our tracker against Stone Soup's GNN and JPDA on the scenario set.

Reproducible: ``python bench/track_quality.py`` (``--help`` for options; needs the test extra
for Stone Soup). Prints a Markdown table, one row per scenario and tracker.

**Offline (the default).** For each scenario (every shipped one by default) the simulator's
truth and the detections it would send (``gateway.scoring.replay``: the Detection events the
daemon makes of its frames) go, in the same run, to

* ``ours``: the fusion processor's tracker with the shipped options
  (``FusionProcessor("fusion", FusionConfig()).tracker``, ticked once a second of data time);
* ``gnn`` and ``jpda``: Stone Soup ``MultiTargetTracker`` with ``GNNWith2DAssignment`` and
  ``MultiTargetMixtureTracker`` with ``JPDA``, configured alike: a constant-velocity Kalman
  filter (``--q`` m²/s³ per axis), each detection's own σ as its measurement noise, a
  Mahalanobis gate of ``--gate``, tracks confirmed after ``--confirm`` updates and deleted
  ``--delete-after`` seconds after their last update. Each sensor frame (one airframe,
  sensor and time) is one scan.

Every tracker's confirmed tracks are scored by ``gateway.scoring.score`` against the truth
(GOSPA c = 100 m, p = 2, α = 2, mean per second); detections/s is wall time inside the tracker
only (scoring and event construction for Stone Soup excluded; ours includes building its
Track events, which is its output), the fastest of ``--repeat`` interleaved runs of each.

**Through the daemon (``--run``).** ``--run --speed 1 --speed 4`` plays each scenario with
``fischer-gateway simulate --scenario X --truth T`` into ``fischer-gateway run`` (one link,
the ``fusion`` processor with ``speed_scale`` set to the speed, ``counter_uas`` with the
scenario's batteries, a jsonl archive, an ``ra180`` sink to a UDP port this script listens on
as the radio net) on loopback, then scores the archive with ``fischer-gateway score`` and
counts the Ra 180 "new target" messages per hostile target: the numbers an operator gets.
Each message is traced to the track it announces (its target number, grid reference and
time against the archive's Track events, ``gateway.scoring.announce``) and counts for the
target the scorer matched that track to; the count by nearest position alone (10 m grid
references, 300 m radius) is in the JSON as ``ra180_new_by_position``, for comparison.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Literal

from gateway.domain.geodesy import from_mgrs
from gateway.events import Detection
from gateway.scoring.announce import announcements_by_track
from gateway.scoring.files import archive_tracks, read_truth, tracks_from_events
from gateway.scoring.model import Plane, TrackReport, Tracks, TruthRun
from gateway.scoring.replay import frames, replay, scenario_detections, scenario_truth
from gateway.scoring.score import Score, announcements_per_target, score
from gateway.sim.scenario import load_scenario, shipped_scenarios
from processors.fusion import FusionConfig, FusionProcessor
from sinks.ra180.cdm import Cdm, CdmError, parse_cdm

TRACKERS = ("ours", "gnn", "jpda")


@dataclass(frozen=True)
class StoneSoupSettings:
    """The configuration shared by both Stone Soup trackers."""

    q: float = 1.0
    gate: float = 3.0
    confirm: int = 3
    delete_after_s: float = 5.0
    velocity_prior_mps: float = 40.0
    prob_detect: float = 0.9
    clutter_density: float = 1e-9


@dataclass
class Row:
    """One scenario through one tracker."""

    scenario: str
    tracker: str
    detections: int
    seconds: float
    result: Score

    @property
    def rate(self) -> float:
        """Detections per second of wall time inside the tracker."""
        return self.detections / self.seconds if self.seconds > 0 else math.inf


def run_ours(events: Sequence[Detection], truth: TruthRun) -> tuple[Tracks, float]:
    """Our tracker, through the fusion processor's public surface."""
    processor = FusionProcessor("fusion", FusionConfig())
    started = time.perf_counter()
    published = replay(events, processor.tracker)
    elapsed = time.perf_counter() - started
    return tracks_from_events(published, truth.plane), elapsed


def run_stonesoup(
    kind: str, events: Sequence[Detection], plane: Plane, s: StoneSoupSettings
) -> tuple[Tracks, float]:
    """Stone Soup as a GNN (``kind`` "gnn") or JPDA ("jpda") tracker on ``events``."""
    from datetime import timedelta

    import numpy as np
    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.dataassociator.probability import JPDA
    from stonesoup.deleter.time import UpdateTimeDeleter
    from stonesoup.gater.distance import DistanceGater
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.hypothesiser.probability import PDAHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.measures import Mahalanobis
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import (
        CombinedLinearGaussianTransitionModel,
        ConstantVelocity,
    )
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.tracker.simple import MultiTargetMixtureTracker, MultiTargetTracker
    from stonesoup.types.detection import Detection as SsDetection
    from stonesoup.types.state import GaussianState

    axis = ConstantVelocity(s.q)
    transition = CombinedLinearGaussianTransitionModel([axis, axis])
    models: dict[float, LinearGaussian] = {}

    def model(sigma: float) -> LinearGaussian:
        if sigma not in models:
            var = max(sigma, 1.0) ** 2
            models[sigma] = LinearGaussian(
                ndim_state=4, mapping=(0, 2), noise_covar=np.diag([var, var])
            )
        return models[sigma]

    from stonesoup.updater.kalman import KalmanUpdater

    predictor = KalmanPredictor(transition)
    updater = KalmanUpdater(model(10.0))
    gnn_hypothesiser = DistanceHypothesiser(
        predictor, updater, measure=Mahalanobis(), missed_distance=s.gate
    )
    deleter = UpdateTimeDeleter(timedelta(seconds=s.delete_after_s))
    v2 = s.velocity_prior_mps**2
    initiator = MultiMeasurementInitiator(
        prior_state=GaussianState(np.zeros((4, 1)), np.diag([0.0, v2, 0.0, v2])),
        measurement_model=None,
        deleter=deleter,
        data_associator=GNNWith2DAssignment(gnn_hypothesiser),
        updater=updater,
        min_points=s.confirm,
    )
    scans = []
    for frame in frames(events):
        at = frame[0].time
        found = set()
        for d in frame:
            x, y = plane.xy(d.position.lat_deg, d.position.lon_deg)
            found.add(SsDetection([[x], [y]], timestamp=at, measurement_model=model(d.sigma_h_m)))
        scans.append((at, found))
    tracker: MultiTargetTracker | MultiTargetMixtureTracker
    if kind == "gnn":
        tracker = MultiTargetTracker(
            initiator=initiator,
            deleter=deleter,
            detector=iter(scans),
            data_associator=GNNWith2DAssignment(gnn_hypothesiser),
            updater=updater,
        )
    else:
        pda = PDAHypothesiser(
            predictor,
            updater,
            clutter_spatial_density=s.clutter_density,
            prob_detect=s.prob_detect,
        )
        tracker = MultiTargetMixtureTracker(
            initiator=initiator,
            deleter=deleter,
            detector=iter(scans),
            data_associator=JPDA(DistanceGater(pda, Mahalanobis(), gate_threshold=s.gate)),
            updater=updater,
        )
    states: list[tuple[datetime, list[tuple[str, float, float, float, float]]]] = []
    started = time.perf_counter()
    for at, live in tracker:
        states.append((at, [(t.id, *(float(v) for v in t.state_vector.ravel()[:4])) for t in live]))
    elapsed = time.perf_counter() - started
    tracks = Tracks()
    alive: set[str] = set()
    for at, live in states:
        unix_s = at.timestamp()
        now = set()
        for track_id, x, vx, y, vy in live:
            now.add(track_id)
            status = "updated" if track_id in alive else "created"
            tracks.add(track_id, TrackReport(unix_s, x, y, vy, vx, status))
        for gone in alive - now:
            last = tracks.reports[gone][-1]
            tracks.add(gone, TrackReport(unix_s, last.x, last.y, last.vn, last.ve, "lost"))
        alive = now
    tracks.sort()
    return tracks, elapsed


def offline(
    names: Sequence[str], trackers: Sequence[str], s: StoneSoupSettings, repeat: int = 5
) -> list[Row]:
    """Every scenario through every tracker, offline; each run ``repeat`` times, the trackers
    interleaved, its fastest time kept (each at its own capacity: a run slowed by another
    process on the machine says nothing about the tracker). The runs give the same tracks."""
    rows = []
    for name in names:
        scenario = load_scenario(name)
        events = scenario_detections(scenario)
        truth = scenario_truth(scenario)
        best: dict[str, tuple[Tracks, float]] = {}
        for _ in range(max(1, repeat)):
            for kind in trackers:
                if kind == "ours":
                    tracks, elapsed = run_ours(events, truth)
                else:
                    tracks, elapsed = run_stonesoup(kind, events, truth.plane, s)
                if kind not in best or elapsed < best[kind][1]:
                    best[kind] = (best.get(kind, (tracks, 0.0))[0], elapsed)
        for kind in trackers:
            tracks, elapsed = best[kind]
            rows.append(Row(name, kind, len(events), elapsed, score(truth, tracks)))
    return rows


def _pct(x: float) -> str:
    return "-" if math.isnan(x) else f"{100 * x:.0f} %"


def _num(x: float, digits: int = 1) -> str:
    return "-" if math.isnan(x) else f"{x:.{digits}f}"


def table(rows: Sequence[Row]) -> str:
    """The Markdown table of ``rows``."""
    out = [
        "| scenario | tracker | GOSPA m | tracks/target | false tracks | ID switches "
        "| RMSE m | speed err p90 m/s | course err p90 ° | with velocity | detections/s |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        s = r.result
        out.append(
            f"| {r.scenario} | {r.tracker} | {s.gospa:.1f} | {_num(s.tracks_per_target, 2)} "
            f"| {s.false_tracks}/{s.track_ids} ({_pct(s.false_track_share)}) | {s.id_switches} "
            f"| {_num(s.position_rmse_m)} | {_num(s.speed_error_p90)} "
            f"| {_num(s.course_error_p90, 0)} | {_pct(s.velocity_share)} | {r.rate:,.0f} |"
        )
    return "\n".join(out)


def over_seeds(names: Sequence[str], s: StoneSoupSettings, seeds: int) -> str:
    """GOSPA of ours and Stone Soup's GNN on each scenario drawn with ``seeds`` seeds (the
    shipped one and the next ones): the shipped draw is one sample of the sensors' noise."""
    out = [
        f"GOSPA over {seeds} draws of each scenario's noise (seeds from the shipped one up):",
        "",
        "| scenario | ours, mean | gnn, mean | ours better or equal in |",
        "| --- | ---: | ---: | ---: |",
    ]
    for name in names:
        base = load_scenario(name)
        mine, theirs = [], []
        for k in range(seeds):
            scenario = base.model_copy(update={"seed": base.seed + k})
            events = scenario_detections(scenario)
            truth = scenario_truth(scenario)
            mine.append(score(truth, run_ours(events, truth)[0]).gospa)
            theirs.append(score(truth, run_stonesoup("gnn", events, truth.plane, s)[0]).gospa)
        wins = sum(a <= b for a, b in zip(mine, theirs, strict=True))
        out.append(
            f"| {name} | {sum(mine) / seeds:.2f} | {sum(theirs) / seeds:.2f} | {wins}/{seeds} |"
        )
    return "\n".join(out)


def ratios(rows: Sequence[Row]) -> str:
    """Our rate over each Stone Soup tracker's, per scenario and over the whole set."""
    by = {(r.scenario, r.tracker): r for r in rows}
    lines = []
    for other in ("gnn", "jpda"):
        per = [
            by[(r.scenario, "ours")].rate / r.rate
            for r in rows
            if r.tracker == other and (r.scenario, "ours") in by
        ]
        if per:
            mine = [r for r in rows if r.tracker == "ours"]
            theirs = [r for r in rows if r.tracker == other]
            whole = (sum(r.detections for r in mine) / sum(r.seconds for r in mine)) / (
                sum(r.detections for r in theirs) / sum(r.seconds for r in theirs)
            )
            lines.append(
                f"ours / {other}: {min(per):.1f}× to {max(per):.1f}× per scenario, "
                f"{whole:.1f}× over the set"
            )
    return "\n".join(lines)


# --- through the daemon ---------------------------------------------------------------


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _node_config(
    workdir: Path, name: str, port: int, speed: float, radio_port: int
) -> tuple[Path, Path]:
    scenario = load_scenario(name)
    archive = workdir / f"{name}-x{speed:g}.jsonl"
    airframes = "\n".join(
        f"  - id: {a.id}\n    sysid: {a.sysid}\n"
        f"    links: [{{uri: 'udp://127.0.0.1:{port}', security: unsecured, name: fleet}}]"
        for a in scenario.airframes
    )
    batteries = [
        {
            "id": b.id,
            "lat_deg": b.lat_deg,
            "lon_deg": b.lon_deg,
            "alt_msl_m": b.alt_msl_m,
            "effectors": list(b.effectors),
        }
        for b in scenario.batteries
    ]
    cuas = (
        f"  - {{name: cuas, type: counter_uas, options: {{batteries: {json.dumps(batteries)}}}}}\n"
        if batteries
        else ""
    )
    config = workdir / f"{name}-x{speed:g}.yaml"
    # --speed compresses time: targets appear that many times faster, so the tracker's speed
    # priors and time constants are scaled with it (speed_scale, docs/counter-uas.md).
    config.write_text(
        f"""gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
{airframes}
processors:
  - {{name: fusion, type: fusion, options: {{speed_scale: {speed:g}}}}}
{cuas}sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
  - {{name: radio, type: ra180, options: {{udp: {{host: 127.0.0.1, port: {radio_port}}}}}}}
routes:
  - {{kinds: [track, handoff], sinks: [archive]}}
  - {{kinds: [track], sinks: [radio]}}
"""
    )
    return config, archive


def _started(proc: subprocess.Popen[bytes], timeout_s: float) -> threading.Thread:
    """Wait for the daemon's ``gateway_started``; a thread then drains its log."""
    seen = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if b"gateway_started" in line:
                seen.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    if not seen.wait(timeout_s):
        raise RuntimeError(f"the daemon did not start within {timeout_s} s")
    return reader


class RadioNet:
    """The Ra 180 net's side: every CDM datagram with the time it was heard."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = int(self.sock.getsockname()[1])
        self.heard: list[tuple[float, str]] = []
        self.precision_m: Literal[1, 10] = 10  # the ra180 sink's default mgrs_precision_m
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(2048)
            except TimeoutError:
                continue
            self.heard.append((time.time(), data.decode("ascii", "replace")))

    def close(self) -> None:
        """Stop listening."""
        self._stop.set()
        self._thread.join(5)
        self.sock.close()

    def messages(self) -> list[tuple[float, Cdm]]:
        """Every CDM heard, with the time it was heard."""
        out = []
        for when, text in self.heard:
            with contextlib.suppress(CdmError):
                out.append((when, parse_cdm(text)))
        return out

    def new_by_position(self, truth: TruthRun) -> tuple[dict[str, int], int]:
        """ "MAL" (new target) messages per hostile target by the target nearest each one's
        grid reference (within 300 m: the net hears a position up to a budget's delay old),
        and those matching none. Coarse: a 10 m reference of a track's early estimate can
        be nearer a neighbour 30 m away."""
        heard = []
        for when, cdm in self.messages():
            if cdm.type == "MAL":
                where = from_mgrs(cdm.mgrs)
                heard.append((when, *truth.plane.xy(where.lat_deg, where.lon_deg)))
        return announcements_per_target(truth, heard, 300.0)

    def new_by_track(
        self, truth: TruthRun, archive: Path, tracks_of_target: dict[str, list[str]]
    ) -> tuple[dict[str, int], int]:
        """ "MAL" messages per hostile target, each traced to the track it announces; and
        those not traced to a track matched to a target."""
        hostile = {t.target for f in truth.frames for t in f.targets if t.affiliation == "hostile"}
        counted = announcements_by_track(
            [cdm for _, cdm in self.messages()],
            archive_tracks([archive]),
            tracks_of_target,
            hostile,
            self.precision_m,
        )
        return counted.per_target, counted.untraced + counted.false_track


def through_run(name: str, speed: float, workdir: Path) -> dict[str, object]:
    """One scenario through ``fischer-gateway run`` at ``speed``; the scorer's JSON."""
    port = _free_udp_port()
    radio = RadioNet()
    config, archive = _node_config(workdir, name, port, speed, radio.port)
    truth = workdir / f"{name}-x{speed:g}.truth.jsonl"
    gateway = [sys.executable, "-m", "gateway"]
    daemon = subprocess.Popen(
        [*gateway, "run", "--config", str(config)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        reader = _started(daemon, 60)
        target = f"udp://127.0.0.1:{port}"
        play = ["simulate", "--scenario", name, "--to", target, "--speed", str(speed)]
        subprocess.run(
            [*gateway, *play, "--truth", str(truth)],
            check=True,
            capture_output=True,
        )
        time.sleep(2.0)  # the archive's last batch
    finally:
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(30)
        radio.close()
    reader.join(10)
    scored = subprocess.run(
        [*gateway, "score", "--truth", str(truth), "--tracks", str(archive), "--json"],
        check=True,
        capture_output=True,
    )
    result: dict[str, object] = json.loads(scored.stdout)
    if not load_scenario(name).batteries:
        result["cues_per_munition"] = {}  # no battery, no counter_uas: no cue expected
    run_truth = read_truth(truth)
    tracks_of = result.get("tracks_of_target")
    assert isinstance(tracks_of, dict)
    news, unmatched = radio.new_by_track(run_truth, archive, tracks_of)
    result["ra180_new_per_target"] = news
    result["ra180_new_unmatched"] = unmatched
    near, far = radio.new_by_position(run_truth)
    result["ra180_new_by_position"] = near
    result["ra180_new_by_position_unmatched"] = far
    return result


def _counts(per: object, unmatched: object) -> str:
    if not isinstance(per, dict):
        return "-"
    values = sorted(per.values())
    text = f"{min(values)}–{max(values)}" if values else "-"
    return f"{text} (+{unmatched} unmatched)" if unmatched else text


def run_table(results: Sequence[tuple[str, float, dict[str, object]]]) -> str:
    """The Markdown table of the through-``run`` results."""

    def num(value: object, digits: int = 1) -> str:
        return "-" if not isinstance(value, int | float) else f"{value:.{digits}f}"

    out = [
        "| scenario | speed | GOSPA m | tracks/target | false tracks | ID switches "
        "| speed err p90 m/s | with velocity | cues per munition | Ra 180 new per target |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- |",
    ]
    for name, speed, r in results:
        cues = r.get("cues_per_munition") or {}
        assert isinstance(cues, dict)
        share = r.get("velocity_share")
        out.append(
            f"| {name} | {speed:g} | {num(r['gospa'])} | {num(r['tracks_per_target'], 2)} "
            f"| {r['false_tracks']}/{r['track_ids']} | {r['id_switches']} "
            f"| {num(r['speed_error_p90'])} "
            f"| {num(100 * share if isinstance(share, float) else None, 0)} % "
            f"| {' '.join(f'{k}:{v}' for k, v in cues.items()) or '-'} "
            f"| {_counts(r.get('ra180_new_per_target'), r.get('ra180_new_unmatched'))} |"
        )
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the options, run, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", action="append", default=None, help="default: all")
    parser.add_argument("--tracker", action="append", choices=TRACKERS, default=None)
    parser.add_argument("--q", type=float, default=1.0, help="CV process noise, m²/s³")
    parser.add_argument("--gate", type=float, default=3.0, help="Mahalanobis gate")
    parser.add_argument("--confirm", type=int, default=3, help="updates to confirm (M)")
    parser.add_argument("--delete-after", type=float, default=5.0, help="seconds unupdated")
    parser.add_argument("--run", action="store_true", help="through fischer-gateway run")
    parser.add_argument("--speed", type=float, action="append", default=None)
    parser.add_argument("--repeat", type=int, default=5, help="runs per tracker; fastest kept")
    parser.add_argument(
        "--seeds", type=int, default=0, help="also GOSPA over this many noise draws (ours, gnn)"
    )
    args = parser.parse_args(argv)
    names = args.scenario or shipped_scenarios()
    print(f"{platform.python_implementation()} {platform.python_version()}, {os.cpu_count()} CPUs")
    if args.run:
        results = []
        with tempfile.TemporaryDirectory(prefix="fischer-tracking-") as tmp:
            for speed in args.speed or [1.0, 4.0]:
                for name in names:
                    results.append((name, speed, through_run(name, speed, Path(tmp))))
                    print(f"{name} at speed {speed:g}: done", file=sys.stderr)
        print(run_table(results))
        return 0
    settings = StoneSoupSettings(
        q=args.q, gate=args.gate, confirm=args.confirm, delete_after_s=args.delete_after
    )
    print(
        f"Stone Soup: CV q={settings.q} m²/s³, Mahalanobis gate {settings.gate}, confirmed "
        f"after {settings.confirm} updates, deleted {settings.delete_after_s:g} s after the "
        f"last; JPDA Pd={settings.prob_detect}, clutter {settings.clutter_density:g}/m²"
    )
    rows = offline(names, args.tracker or list(TRACKERS), settings, args.repeat)
    print(table(rows))
    print(ratios(rows))
    if args.seeds:
        print()
        print(over_seeds(names, settings, args.seeds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
