"""Ingest benchmark: fischer-gateway against a bare pymavlink parse loop (and MAVProxy).

Reproducible: ``python bench/ingest.py`` (``--help`` for options). Prints a Markdown table.

Part A, the pipeline on one core (no sockets): the same datagrams (N airframes x a realistic
message mix, optionally sealed in the tunnel) go through (1) a bare pymavlink
``parse_buffer`` loop and (2) the gateway's ingest → normalise → bus → five sink runners,
run until every sink has its last event. The ratio is (2)/(1) in messages per second.
(2) runs twice: with the loop let through every 256 datagrams (a daemon under load: uvloop
reads up to 32 ready datagrams per loop pass, and telemetry is coalesced per pass) and with
every datagram its own loop pass (a daemon below saturation: each datagram is a snapshot,
published and delivered to the five sinks on its own).

Part B, the daemon over UDP loopback: ``fischer-gateway run`` in its own process with five
null sinks, fed by a sender process (sealing each frame afresh). First its capacity: the
highest offered rate with < 0.1 % loss; then 10 % and 80 % of that. Reports loss (frames the
gateway counted vs sent), the ingest→sink delivery latency p50/p99/p99.9 from the gateway's
own histogram (kernel socket time excluded), CPU and RSS of the daemon.
With ``--mavproxy`` and MAVProxy installed, the same load through ``mavproxy.py`` forwarding.

``--floor`` adds the floor of the per-pass column: the same run, a datagram per loop pass,
with ``Bus.publish`` doing nothing (tunnel open, decode, normalise and the loop pass only, so
no sink is fed), and bare pymavlink with a loop pass per datagram; each ÷ bare pymavlink.
No delivery design brings the per-pass ratio above the first.
"""

from __future__ import annotations

import argparse
import gc
import math
import multiprocessing
import os
import platform
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from datetime import UTC, datetime
from pathlib import Path
from unittest import mock

import anyio
import anyio.lowlevel
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.app import Gateway
from gateway.config import Config
from gateway.fleet.security.tunnel import DayKeys, Sealer
from gateway.flow.bus import Bus
from gateway.ops.gcsetup import settle_gc
from gateway.ops.logsetup import configure_logging
from gateway.sim.airframe import SimProfile, SimulatedAirframe
from gateway.testing import NullSink

MASTER = bytes(range(32))
SINKS = 5


def airframe_id(i: int) -> str:
    return f"F26E-{i:04d}"


def make_datagrams(
    airframes: int, seconds: float, tunnel: bool, ids: list[str] | None = None
) -> list[bytes]:
    """One datagram per frame, interleaved across airframes in time order.

    ``ids``, when given, receives the airframe id of each datagram.
    """
    profile = SimProfile(position_hz=10, gps_hz=0.0001, status_hz=2, heartbeat_hz=1)
    sims = [SimulatedAirframe(i % 250 + 1, profile, phase_rad=i) for i in range(airframes)]
    keys = DayKeys(master=MASTER)
    sealers = [Sealer(airframe_id(i), keys, lambda: datetime.now(UTC)) for i in range(airframes)]
    out: list[bytes] = []
    t = 0.0
    while t < seconds:
        for i, sim in enumerate(sims):
            for frame in sim.frames_at(t):
                out.append(sealers[i].seal(frame) if tunnel else frame)
                if ids is not None:
                    ids.append(airframe_id(i))
        t += 0.05
    return out


def config(airframes: int, tunnel: bool, port: int, key_file: str | None) -> Config:
    return Config.model_validate(
        {
            "gateway": {"shutdown_deadline_s": 2},
            "health": {"port": 0},
            "tunnel": {"master_key_file": key_file} if key_file else {},
            "airframes": [
                {
                    "id": airframe_id(i),
                    "sysid": i % 250 + 1,
                    "links": [
                        {
                            "uri": f"udp://127.0.0.1:{port}",
                            "security": "tunnel" if tunnel else "unsecured",
                            "name": "bench",
                        }
                    ],
                }
                for i in range(min(airframes, 250))
            ],
            "sinks": [
                {"name": f"null{n}", "type": "null", "queue_max": 100_000, "batch_max": 500}
                for n in range(SINKS)
            ],
            "routes": [{"sinks": [f"null{n}" for n in range(SINKS)]}],
        }
    )


def bare_pymavlink(datagrams: list[bytes], tunnel: bool) -> float:
    """Messages per second of pymavlink alone (one parser, one parse_buffer per datagram)."""
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    if tunnel:
        from gateway.fleet.security.tunnel import TunnelOpener

        opener = TunnelOpener(
            DayKeys(master=MASTER),
            frozenset(airframe_id(i) for i in range(250)),
            lambda: datetime.now(UTC),
            freshness_s=3600,
        )
        # The datagrams were sealed before this opener existed (and are reused across runs):
        # lift the restart-replay rule, which would refuse every one of them here.
        opener.started_ms = 0
    start = time.perf_counter()
    count = 0
    for data in datagrams:
        payload = opener.open_frame(data, "b").payload if tunnel else data
        count += len(parser.parse_buffer(payload) or ())
    return count / (time.perf_counter() - start)


def _publish_nothing(self: Bus, event: object) -> bool:
    return True


def bare_pymavlink_passes(datagrams: list[bytes]) -> float:
    """Messages per second of pymavlink alone with a pass of the event loop per datagram."""
    parser = mav.MAVLink(None)
    parser.robust_parsing = True

    async def run() -> float:
        start = time.perf_counter()
        count = 0
        for data in datagrams:
            count += len(parser.parse_buffer(data) or ())
            await anyio.lowlevel.checkpoint()
        return count / (time.perf_counter() - start)

    return anyio.run(run, backend_options={"use_uvloop": True})


def gateway_pipeline(
    datagrams: list[bytes],
    airframes: int,
    tunnel: bool,
    key: str,
    per_pass: int = 256,
    *,
    bus: bool = True,
) -> float:
    """Messages per second through ingest, normalise, bus and five sink runners.

    ``per_pass``: datagrams handed to ingest between two passes of the event loop.
    ``bus`` False: ``Bus.publish`` does nothing (the floor: no sink is fed).
    """
    if not bus:
        with mock.patch.object(Bus, "publish", _publish_nothing):
            return gateway_pipeline(datagrams, airframes, tunnel, key, per_pass)
    cfg = config(airframes, tunnel, 0, key if tunnel else None)
    sinks = {f"null{n}": NullSink(f"null{n}") for n in range(SINKS)}
    gateway = Gateway(cfg, sinks=dict(sinks))
    if tunnel:
        assert gateway.fleet.security.opener is not None
        gateway.fleet.security.opener.freshness_s = 3600
        gateway.fleet.security.opener.started_ms = 0  # sealed before it existed: see bare_pymavlink
    total = len(datagrams)

    async def run() -> float:
        async with anyio.create_task_group() as tg:
            for runner in gateway.runners.values():
                await tg.start(runner.run)
            on_data = gateway.fleet.ingest.on_data
            start = time.perf_counter()
            for index, data in enumerate(datagrams):
                on_data("bench", "peer", data)
                if index % per_pass == 0:
                    await (
                        anyio.lowlevel.checkpoint()
                    )  # let the sink runners drain, as the loop would
            for runner in gateway.runners.values():
                runner.stop()
            for runner in gateway.runners.values():
                await runner.wait_done()
            elapsed = time.perf_counter() - start
            tg.cancel_scope.cancel()
        return elapsed

    from gateway.fleet.ingest import LinkIntake

    gateway.fleet.ingest.register_link(
        LinkIntake("bench", "tunnel" if tunnel else "unsecured", is_stream=False)
    )
    # As ``fischer-gateway run`` does once the gateway is built; undone after, so what this
    # process measures next (pymavlink's side of a ratio) runs at CPython's defaults.
    threshold, frozen = gc.get_threshold(), gc.get_freeze_count()
    settle_gc()
    try:
        elapsed = anyio.run(run, backend_options={"use_uvloop": True})
    finally:
        gc.set_threshold(*threshold)
        if not frozen:
            gc.unfreeze()
    frames = gateway.instruments.link_frames.labels("bench").value
    assert frames == total, (frames, total)
    return total / elapsed


def sender(
    port: int,
    datagrams: list[bytes],
    rate: float,
    seconds: float,
    out: object,
    ids: list[str] | None = None,
) -> None:
    """Send ``datagrams`` round-robin at ``rate`` per second for ``seconds`` (own process).

    With ``ids`` (the airframe of each datagram) every send is sealed afresh, since a
    re-sent sealed frame would rightly be rejected as a replay.
    """
    sealers = {}
    if ids is not None:
        keys = DayKeys(master=MASTER)
        sealers = {i: Sealer(i, keys, lambda: datetime.now(UTC)) for i in set(ids)}
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect(("127.0.0.1", port))
    start = time.perf_counter()
    sent = 0
    n = len(datagrams)
    while True:
        now = time.perf_counter() - start
        if now >= seconds:
            break
        due = int(now * rate)
        while sent < due:
            index = sent % n
            data = datagrams[index]
            sock.send(sealers[ids[index]].seal(data) if ids is not None else data)
            sent += 1
        time.sleep(0.0005)
    out.value = sent  # type: ignore[attr-defined]


def metric(text: str, name: str, labels: str = "") -> float:
    total = 0.0
    for line in text.splitlines():
        if line.startswith((name + "{" + labels, name + " ")):
            total += float(line.rsplit(" ", 1)[1])
    return total


def quantile(text: str, q: float) -> float:
    """A quantile of the summed delivery-latency histogram, by linear interpolation (ms)."""
    buckets: dict[float, float] = {}
    for line in text.splitlines():
        if line.startswith("fg_sink_delivery_latency_seconds_bucket"):
            le = re.search(r'le="([^"]+)"', line)
            assert le is not None
            bound = math.inf if le.group(1) == "+Inf" else float(le.group(1))
            buckets[bound] = buckets.get(bound, 0) + float(line.rsplit(" ", 1)[1])
    ordered = sorted(buckets.items())
    total = ordered[-1][1]
    target = q * total
    prev_bound, prev_count = 0.0, 0.0
    for bound, count in ordered:
        if count >= target:
            if math.isinf(bound):
                return prev_bound * 1000
            share = (target - prev_count) / max(count - prev_count, 1)
            return (prev_bound + share * (bound - prev_bound)) * 1000
        prev_bound, prev_count = bound, count
    return math.nan


def daemon_run(
    datagrams: list[bytes],
    ids: list[str],
    airframes: int,
    tunnel: bool,
    rate: float,
    seconds: float,
    key: str,
) -> dict[str, float]:
    """The daemon in its own process under a fixed load; loss, latency, CPU, RSS."""
    port, health = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    cfg = config(airframes, tunnel, port, key if tunnel else None).model_dump(mode="json")
    cfg["health"]["port"] = health
    if tunnel:
        cfg["tunnel"]["freshness_s"] = 3600
    import yaml

    path = Path(tempfile.mkdtemp()) / "bench.yaml"
    path.write_text(yaml.safe_dump(cfg))
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway", "run", "--config", str(path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        url = f"http://127.0.0.1:{health}"
        wait_ready(health, proc)
        cpu0 = cpu_s(proc.pid)
        sent = multiprocessing.Value("q", 0)
        child = multiprocessing.Process(
            target=sender, args=(port, datagrams, rate, seconds, sent, ids if tunnel else None)
        )
        t0 = time.perf_counter()
        child.start()
        child.join()
        time.sleep(0.5)
        wall = time.perf_counter() - t0
        cpu = cpu_s(proc.pid) - cpu0
        text = urllib.request.urlopen(url + "/metrics", timeout=5).read().decode()  # noqa: S310
        frames = metric(text, "fg_link_frames_total")
        return {
            "sent": sent.value,
            "loss_pct": 100.0 * (1 - frames / max(sent.value, 1)),
            "p50_ms": quantile(text, 0.5),
            "p99_ms": quantile(text, 0.99),
            "p999_ms": quantile(text, 0.999),
            "cpu_pct": 100.0 * cpu / wall,
            "rss_mb": _rss_mb(proc.pid),
        }
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=15)


_GIVEN: set[int] = set()


def free_port(kind: socket.SocketKind) -> int:
    """A loopback port free for ``kind`` (SOCK_DGRAM or SOCK_STREAM) at the time of asking.

    Chosen below the kernel's ephemeral range (32768 on): a port from ``bind(0)`` can be
    handed to any process's unbound send before the bench's own process binds it.
    """
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    for _ in range(1_000):
        port = rng.randrange(20_000, 32_000)
        if port in _GIVEN:
            continue
        with socket.socket(socket.AF_INET, kind) as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
        _GIVEN.add(port)
        return port
    raise RuntimeError("no free loopback port in 20000-32000")


def wait_ready(health: int, proc: subprocess.Popen[bytes]) -> None:
    """Wait until the daemon answers /readyz on ``health`` (or has exited)."""
    for _ in range(400):
        if proc.poll() is not None:
            raise RuntimeError(f"the gateway exited {proc.returncode} before it was ready")
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{health}/readyz", timeout=1)
            return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError("the gateway did not become ready")


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return math.nan


def mavproxy_exe() -> str | None:
    """The ``mavproxy.py`` script on PATH or beside this Python (None if not installed)."""
    return shutil.which("mavproxy.py") or shutil.which(
        "mavproxy.py", path=str(Path(sys.executable).parent)
    )


def mavproxy_rate(datagrams: list[bytes], rate: float, seconds: float) -> float | None:
    """Share of datagrams MAVProxy forwards at ``rate`` (None if MAVProxy is absent)."""
    exe = mavproxy_exe()
    if exe is None:
        return None
    ports = [free_port(socket.SOCK_DGRAM) for _ in range(2)]
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    out.bind(("127.0.0.1", ports[1]))
    out.settimeout(0.2)
    proc = subprocess.Popen(
        [exe, f"--master=udpin:127.0.0.1:{ports[0]}", f"--out=udp:127.0.0.1:{ports[1]}",
         "--daemon", "--non-interactive", "--nowait", "--state-basedir", tempfile.mkdtemp()],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        time.sleep(3)
        sent = multiprocessing.Value("q", 0)
        child = multiprocessing.Process(
            target=sender, args=(ports[0], datagrams, rate, seconds, sent)
        )
        child.start()
        received = 0
        deadline = time.perf_counter() + seconds + 2
        while time.perf_counter() < deadline:
            try:
                received += len(out.recv(65536)) > 0
            except TimeoutError:
                continue
        child.join()
        return received / max(sent.value, 1)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        out.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--airframes", default="1,100,250", help="at most 250: 8-bit sysids")
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--mavproxy", action="store_true")
    parser.add_argument(
        "--pipeline-only", action="store_true", help="part A only (no daemon over UDP)"
    )
    parser.add_argument(
        "--floor",
        action="store_true",
        help="also the per-pass floor: the bus doing nothing, and bare pymavlink with a pass",
    )
    args = parser.parse_args()
    configure_logging("warning", sys.stderr)
    key_dir = Path(tempfile.mkdtemp())
    key = key_dir / "master.key"
    key.write_text(MASTER.hex())
    key.chmod(0o600)
    print(f"# ingest benchmark, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}, {platform.platform()}")  # fmt: skip
    print("\n## A. pipeline on one core (messages/s)\n")
    print(
        "| airframes | tunnel | pymavlink (+ our AES-GCM open when on) | gateway | ratio "
        "| ratio vs plain pymavlink | gateway, a datagram per loop pass | ratio |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    capacity: dict[tuple[int, bool], float] = {}
    bare_rates: dict[int, float] = {}
    for n in (int(x) for x in args.airframes.split(",")):
        for tunnel in (False, True):
            datagrams = make_datagrams(n, max(1.0, 40_000 / (n * 13)), tunnel)
            bare = bare_pymavlink(datagrams, tunnel)
            ours = gateway_pipeline(datagrams, n, tunnel, str(key))
            single = gateway_pipeline(datagrams, n, tunnel, str(key), per_pass=1)
            capacity[(n, tunnel)] = ours
            if not tunnel:  # the loop runs tunnel off first
                bare_rates[n] = bare
            mode = "on" if tunnel else "off"
            print(
                f"| {n} | {mode} | {bare:,.0f} | {ours:,.0f} | {ours / bare:.2f} "
                f"| {ours / bare_rates[n]:.2f} | {single:,.0f} | {single / bare:.3f} |"
            )
    if args.floor:
        print("\n## A'. floor of the per-pass column (messages/s, a datagram per loop pass)\n")
        print(
            "| airframes | tunnel | pymavlink | gateway, bus doing nothing | ratio "
            "| pymavlink, a loop pass per datagram | ratio |"
        )
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for n in (int(x) for x in args.airframes.split(",")):
            for tunnel in (False, True):
                datagrams = make_datagrams(n, max(1.0, 40_000 / (n * 13)), tunnel)
                bare = bare_pymavlink(datagrams, tunnel)
                floor = gateway_pipeline(datagrams, n, tunnel, str(key), per_pass=1, bus=False)
                passes = "" if tunnel else f"{bare_pymavlink_passes(datagrams):,.0f}"
                ratio = "" if tunnel else f"{float(passes.replace(',', '')) / bare:.3f}"
                print(
                    f"| {n} | {'on' if tunnel else 'off'} | {bare:,.0f} | {floor:,.0f} "
                    f"| {floor / bare:.3f} | {passes} | {ratio} |"
                )
    if args.pipeline_only:
        return
    print("\n## B. daemon over UDP loopback, tunnel on, 5 null sinks\n")
    print(
        "| airframes | load | offered msg/s | loss % | p50 ms | p99 ms | p99.9 ms "
        "| CPU % | RSS MB |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    sustained: dict[int, float] = {}
    for n in (int(x) for x in args.airframes.split(",")):
        ids: list[str] = []
        datagrams = make_datagrams(n, 2.0, False, ids)
        # Capacity over sockets: the highest offered rate with < 0.1 % loss, searched down
        # from the in-process rate in 15 % steps (the sender holds the other core).
        rate = capacity[(n, True)]
        for _ in range(8):
            r = daemon_run(datagrams, ids, n, True, rate, args.seconds, str(key))
            if r["loss_pct"] < 0.1:
                break
            rate *= 0.85
        sustained[n] = r["sent"] / args.seconds
        rows = [("capacity", r)]
        for share in (0.1, 0.8):
            load = sustained[n] * share
            rows.append(
                (f"{share:.0%}", daemon_run(datagrams, ids, n, True, load, args.seconds, str(key)))
            )
        for label, r in rows:
            print(f"| {n} | {label} | {r['sent'] / args.seconds:,.0f} | {r['loss_pct']:.3f} | "
                  f"{r['p50_ms']:.2f} | {r['p99_ms']:.2f} | {r['p999_ms']:.2f} | "
                  f"{r['cpu_pct']:.0f} | {r['rss_mb']:.0f} |")  # fmt: skip
    if args.mavproxy:
        datagrams = make_datagrams(100, 2.0, False)
        offered = capacity[(100, False)] * 0.8
        share = mavproxy_rate(datagrams, offered, args.seconds)
        if share is None:
            print("\nMAVProxy: not installed (pip install MAVProxy)")
        else:
            ours = sustained.get(100)
            compare = (
                f"; the gateway daemon sustained {ours:,.0f} msg/s over UDP with the tunnel, "
                f"normalising and feeding 5 sinks ({ours / max(share * offered, 1):.1f}x)"
                if ours
                else ""
            )
            print(
                f"\nMAVProxy forwarding (udpin → udp out), 100 airframes, no tunnel, offered "
                f"{offered:,.0f} msg/s: forwarded {share:.1%} = {share * offered:,.0f} msg/s"
                + compare
            )


if __name__ == "__main__":
    main()
