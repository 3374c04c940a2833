"""Detection → GUTE II cue: from the detection that confirms a track to the cue at the battery.

Reproducible: ``python bench/cue.py`` (``--help`` for options; ``--compare TREE`` runs the
daemon from another source tree in the same run, interleaved). Prints a Markdown table.

- The **system under test** is ``python -m gateway run --config FILE`` with the spool on (a
  file), the tunnel, processors ``fusion`` and ``counter_uas`` (one battery), five CoT UDP
  sinks taking detections and tracks (as in ``bench/e2e.py``) and ``--gute`` ``gute2`` sinks,
  each POSTing the cues to its own path of one real GUTE II peer.
- The **peer** is the tests' HTTPS battery (``tests/https_peer.py``: loopback, its own CA,
  client certificates required, HTTP/1.1 keep-alive) in a thread; it stamps
  ``time.monotonic_ns()`` when a cue's request has arrived, and answers 201.
- The **sender** (the main thread) plays one new loitering munition per trial, at its own
  spot around the battery: one detection every ``--gap-ms`` until the first cue for it has
  arrived at every GUTE sink. The detection that confirms the track is the last one sent
  before that; the latency is its send → the cue's arrival at the *last* GUTE sink. A gap
  longer than the latency keeps that attribution exact (a trial whose cue came in later than
  the gap is counted as such, not measured). Each detection is the only one of its sensor
  frame and says so (FISCHER_DETECTION ``frame_size`` 1; ``--frame-size 0`` sends it as a
  sender without the extension, whose frames fusion holds ``frame_wait_s``). A daemon from
  before the extension (``--compare``) reads the same frames without it.
- **Track at the last CoT sink**: the same detection's send → the track's arrival at the
  last of the CoT sinks. The track may come after the cue; the trial waits for it (a gap at
  most) before the next target.

The gateway recommends, it never commands: the cue is a recommendation for the battery's
operator, and this bench only measures how soon the operator's screen has it.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import re
import selectors
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml
from ingest import MASTER, airframe_id, free_port, wait_ready
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.fleet.dialect import fischer_detection
from gateway.fleet.security.tunnel import DayKeys, Sealer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from https_peer import Answer, Head, HttpsPeer  # the tests' HTTPS battery

COT_SINKS = 5
BATTERY = (65.80, 21.70)
AIRFRAMES = 3
LOITERING_MUNITION = 5  # FISCHER_DETECTION class_id
_REVISION = re.compile(r"-r\d+$")
_TRACK_UID = re.compile(rb'uid="[^"]*-trk-([^"]+)"')


class StampingBattery(HttpsPeer):
    """Answers 201 to every POST and stamps the arrival of each cue by path and key."""

    def __init__(self, directory: Path) -> None:
        super().__init__(directory, file_prefix="cue")
        self.lock = threading.Lock()
        #: (path, Idempotency-Key) → arrival, monotonic ns (the first arrival only).
        self.arrivals: dict[tuple[str, str], int] = {}

    def _answer(self, head: Head, body: bytes) -> Answer:
        now = time.monotonic_ns()
        key = head.headers.get("idempotency-key", "")
        with self.lock:
            self.arrivals.setdefault((head.path, key), now)
        return 201, {"status": "accepted", "handoff_id": key}

    def new_cue(self, paths: list[str], seen: set[str]) -> tuple[str, int] | None:
        """A first cue (revision 0) not in ``seen`` that every path has: its key and its
        arrival at the last of them."""
        with self.lock:
            arrivals = list(self.arrivals.items())
        by_key: dict[str, list[int]] = {}
        for (path, key), at in arrivals:
            if path in paths and key not in seen and not _REVISION.search(key):
                by_key.setdefault(key, []).append(at)
        for key, ats in by_key.items():
            if len(ats) == len(paths):
                return key, max(ats)
        return None


class TrackStamps:
    """Stamps the first arrival of each CoT track uid at each CoT sink (its own thread)."""

    def __init__(self, socks: list[socket.socket]) -> None:
        self.socks = socks
        self.lock = threading.Lock()
        #: track uid → arrival at each sink (monotonic ns), first arrival only.
        self.arrivals: dict[bytes, dict[int, int]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> TrackStamps:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)

    def _run(self) -> None:
        selector = selectors.DefaultSelector()
        for n, sock in enumerate(self.socks):
            selector.register(sock, selectors.EVENT_READ, n)
        while not self._stop.is_set():
            for handle, _ in selector.select(0.05):
                sock, sink = handle.fileobj, handle.data
                while True:
                    try:
                        data = sock.recv(65536)  # type: ignore[union-attr]
                    except BlockingIOError:
                        break
                    now = time.monotonic_ns()
                    match = _TRACK_UID.search(data)
                    if match:
                        with self.lock:
                            self.arrivals.setdefault(match.group(1), {}).setdefault(sink, now)
        selector.close()

    def new_track(self, seen: set[bytes], since_ns: int) -> tuple[bytes, int] | None:
        """A track uid not in ``seen``, first heard after ``since_ns``, that every sink has:
        its arrival at the last one."""
        with self.lock:
            for uid, at in self.arrivals.items():
                if uid not in seen and len(at) == len(self.socks) and min(at.values()) > since_ns:
                    return uid, max(at.values())
        return None


def write_config(
    workdir: Path,
    port: int,
    peer: StampingBattery,
    gute: int,
    cot_ports: list[int],
    frame_wait_s: float | None,
) -> Path:
    health = free_port(socket.SOCK_STREAM)
    tls = peer.tls_options()
    fusion = {} if frame_wait_s is None else {"frame_wait_s": frame_wait_s}
    cfg: dict[str, Any] = {
        "gateway": {"shutdown_deadline_s": 2, "log_level": "warning"},
        "health": {"port": health},
        "tunnel": {"master_key_file": str(workdir / "master.key")},
        "spool": {"path": str(workdir / f"spool-{port}.db")},
        "airframes": [
            {
                "id": airframe_id(i),
                "sysid": i + 1,
                "links": [
                    {"uri": f"udp://127.0.0.1:{port}", "security": "tunnel", "name": "bench"}
                ],
            }
            for i in range(AIRFRAMES)
        ],
        "processors": [
            {"name": "fusion", "type": "fusion", "options": fusion},
            {
                "name": "cuas",
                "type": "counter_uas",
                "options": {
                    "batteries": [
                        {
                            "id": "GUTE-1",
                            "lat_deg": BATTERY[0],
                            "lon_deg": BATTERY[1],
                            "effectors": ["EW_COUNTERMEASURES"],
                        }
                    ]
                },
            },
        ],
        "sinks": [
            {
                "name": f"cot{n}",
                "type": "cot",
                "options": {
                    "destinations": [f"udp://127.0.0.1:{p}"],
                    "kinds": ["detection", "track"],
                },
            }
            for n, p in enumerate(cot_ports)
        ]
        + [
            {
                "name": f"gute{n}",
                "type": "gute2",
                "options": {"url": f"https://127.0.0.1:{peer.port}/b{n}", **tls},
            }
            for n in range(gute)
        ],
        "routes": [
            {"sinks": [f"cot{n}" for n in range(len(cot_ports))], "kinds": ["detection", "track"]},
            {"sinks": [f"gute{n}" for n in range(gute)], "kinds": ["handoff"]},
        ],
    }
    path = workdir / f"cue-{port}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def spot(trial: int) -> tuple[int, int]:
    """Trial ``trial``'s target, 3 km from the battery on its own bearing (lat, lon × 1e7)."""
    bearing = math.radians(trial * 7.3 % 360)
    north, east = 3000.0 * math.cos(bearing), 3000.0 * math.sin(bearing)
    lat = BATTERY[0] + north / 111_320.0
    lon = BATTERY[1] + east / (111_320.0 * math.cos(math.radians(BATTERY[0])))
    return round(lat * 1e7), round(lon * 1e7)


def run_daemon(args: argparse.Namespace, tree: Path | None, workdir: Path) -> dict[str, Any]:
    """One daemon, ``args.trials`` targets; latencies in ms and the trials not measured."""
    peer = StampingBattery(workdir / f"pki-{time.monotonic_ns()}")
    paths = [f"/b{n}" for n in range(args.gute)]
    cot_sinks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(COT_SINKS)]
    for sock in cot_sinks:
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
    port = free_port(socket.SOCK_DGRAM)
    latencies: list[float] = []
    to_track: list[float] = []
    late = missed = 0
    with peer.in_thread(), TrackStamps(cot_sinks) as tracks:
        config = write_config(
            workdir,
            port,
            peer,
            args.gute,
            [s.getsockname()[1] for s in cot_sinks],
            args.frame_wait_s,
        )
        env = dict(os.environ)
        if tree is not None:
            env["PYTHONPATH"] = str(tree.resolve())
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", "run", "--config", str(config)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
            cwd=tree,
        )
        try:
            cfg = yaml.safe_load(config.read_text())
            wait_ready(cfg["health"]["port"], proc)
            keys = DayKeys(master=MASTER)
            sealers = [
                Sealer(airframe_id(i), keys, lambda: datetime.now(UTC)) for i in range(AIRFRAMES)
            ]
            packers = [mav.MAVLink(None, srcSystem=i + 1, srcComponent=1) for i in range(AIRFRAMES)]
            out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            out.connect(("127.0.0.1", port))
            gap_ns = int(args.gap_ms * 1e6)
            ident = 0
            seen: set[str] = set()
            seen_tracks: set[bytes] = set()
            for trial in range(1, args.trials + 1):
                lat, lon = spot(trial)
                sent_at = 0
                trial_start = time.monotonic_ns()
                arrived = None
                for _ in range(args.max_detections):
                    ident += 1
                    i = ident % AIRFRAMES
                    frame = fischer_detection(
                        time_usec=int(time.time() * 1e6),
                        detection_id=ident,
                        lat_e7=lat,
                        lon_e7=lon,
                        alt_msl_m=120.0,
                        sigma_h_m=5.0,
                        class_id=LOITERING_MUNITION,
                        sensor=1,
                        confidence_pct=97,
                        subtype="",
                        frame_size=args.frame_size,
                    ).pack(packers[i])
                    payload = sealers[i].seal(frame)
                    sent_at = time.monotonic_ns()
                    out.send(payload)
                    deadline = sent_at + gap_ns
                    while time.monotonic_ns() < deadline:
                        cue = peer.new_cue(paths, seen)
                        if cue is not None:
                            seen.add(cue[0])
                            arrived = cue[1]
                            break
                        time.sleep(0.0002)
                    if arrived is not None:
                        break
                if arrived is None:
                    # Not within a gap of any detection: wait once more, then count it.
                    time.sleep(1.0)
                    cue = peer.new_cue(paths, seen)
                    if cue is None:
                        missed += 1
                    else:
                        seen.add(cue[0])
                        late += 1
                    if (track := tracks.new_track(seen_tracks, trial_start)) is not None:
                        seen_tracks.add(track[0])
                    continue
                latencies.append((arrived - sent_at) / 1e6)
                # The track may reach the CoT sinks after the cue reached the battery: wait
                # for it (a gap at most) so the next trial does not take it for its own.
                track = tracks.new_track(seen_tracks, trial_start)
                while track is None and time.monotonic_ns() < sent_at + gap_ns:
                    time.sleep(0.0002)
                    track = tracks.new_track(seen_tracks, trial_start)
                if track is not None:
                    seen_tracks.add(track[0])
                    to_track.append((track[1] - sent_at) / 1e6)
            out.close()
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            for sock in cot_sinks:
                sock.close()
    return {
        "latencies": sorted(latencies),
        "to_track": sorted(to_track),
        "late": late,
        "missed": missed,
    }


def _pct(ordered: list[float], q: float) -> float:
    if not ordered:
        return float("nan")
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def spread(values: list[float], fmt: str = "{:.2f}") -> str:
    """min / median / max over the rounds."""
    if not values:
        return "-"
    return " / ".join(fmt.format(v) for v in (min(values), statistics.median(values), max(values)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--trials", type=int, default=20, help="targets cued per round")
    parser.add_argument("--gute", type=int, default=5, help="gute2 sinks (one battery path each)")
    parser.add_argument("--gap-ms", type=float, default=150.0, help="between detections")
    parser.add_argument("--max-detections", type=int, default=12, help="per target at most")
    parser.add_argument(
        "--frame-wait-s",
        type=float,
        help="the fusion processor's frame_wait_s (default: its own, 0.05)",
    )
    parser.add_argument(
        "--frame-size",
        type=int,
        default=1,
        choices=range(256),
        metavar="N",
        help="FISCHER_DETECTION frame_size sent (default 1: each detection is its own frame; "
        "0: unknown, as a sender without the extension)",
    )
    parser.add_argument("--compare", type=Path, help="also run the daemon from this tree")
    args = parser.parse_args()
    workdir = Path(tempfile.mkdtemp(prefix="fg-cue-"))
    key = workdir / "master.key"
    key.write_text(MASTER.hex())
    key.chmod(0o600)
    kinds: list[tuple[str, Path | None]] = [("gateway", None)]
    if args.compare:
        kinds.append(("compare", args.compare))
    rows: dict[str, dict[str, list[float]]] = {k: {} for k, _ in kinds}
    for _ in range(args.rounds):
        for kind, tree in kinds:
            result = run_daemon(args, tree, workdir)
            lat, trk = result["latencies"], result["to_track"]
            print(
                f"  {kind}: {len(lat)} cues, p50 {_pct(lat, 0.5):.2f} ms, "
                f"track at the last CoT sink p50 {_pct(trk, 0.5):.2f} ms, "
                f"p90 {_pct(lat, 0.9):.2f} ms, max {max(lat, default=float('nan')):.2f} ms, "
                f"late {result['late']}, missed {result['missed']}",
                file=sys.stderr,
            )
            figures = rows[kind]
            figures.setdefault("p50", []).append(_pct(lat, 0.5))
            figures.setdefault("p90", []).append(_pct(lat, 0.9))
            figures.setdefault("track", []).append(_pct(trk, 0.5))
            figures.setdefault("late", []).append(result["late"] + result["missed"])
    print(f"# detection → GUTE II cue, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}; load average {os.getloadavg()[0]:.1f}"
    )
    print(
        f"command: python bench/cue.py --rounds {args.rounds} --trials {args.trials} "
        f"--gute {args.gute} --frame-size {args.frame_size}; min / median / max of the rounds\n"
    )
    print(
        "| daemon | cue p50 ms | cue p90 ms | track at the last CoT sink p50 ms "
        "| cues later than the gap or missing |"
    )
    print("| --- | --- | --- | --- | --- |")
    names = {"gateway": "this tree", "compare": str(args.compare)}
    for kind, _ in kinds:
        f = rows[kind]
        print(
            f"| {names[kind]} | {spread(f['p50'])} | {spread(f['p90'])} | {spread(f['track'])} "
            f"| {spread(f['late'], '{:.0f}')} |"
        )


if __name__ == "__main__":
    main()
