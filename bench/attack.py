"""Attack benchmark: the daemon's memory and delivery under hostile traffic (docs/security.md).

Reproducible: ``python bench/attack.py`` (``--help`` for options). Prints a Markdown table.

Runs ``fischer-gateway run`` in its own process with a tunnel link and an unsecured link on
loopback, five null sinks, then:

A. Source-port churn: garbage from ``--sources`` distinct (address, port) pairs (127.0.0.0/8
   gives enough addresses), one datagram each to both links. Reports the daemon's RSS before,
   after, and the growth; per-source state would show as growth here.

B. Garbage flood: one process sends garbage to the tunnel port at ``--flood-rate`` datagrams/s
   while a genuine airframe sends sealed frames at ``--genuine-rate`` Hz; reports the share of
   genuine frames the gateway accepted (its own ``fg_link_frames_total``), the flood rate the
   sender achieved and the rate the daemon counted, and the same delivery with no flood.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from datetime import UTC, datetime
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.fleet.security.tunnel import DayKeys, Sealer

MASTER = bytes(range(32))
GARBAGE = bytes(range(40, 80))  # no MAVLink start byte, no tunnel magic


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def write_config(directory: Path, tun: int, open_: int, health: int) -> Path:
    key = directory / "master.key"
    key.write_text(MASTER.hex())
    key.chmod(0o600)
    sinks = "".join(f"  - {{name: n{i}, type: 'null'}}\n" for i in range(5))
    names = ", ".join(f"n{i}" for i in range(5))
    path = directory / "bench.yaml"
    path.write_text(
        f"health: {{port: {health}}}\n"
        f"tunnel: {{master_key_file: '{key}'}}\n"
        "airframes:\n"
        "  - {id: F26E-0001, sysid: 1, links: "
        f"[{{uri: 'udp://127.0.0.1:{tun}', security: tunnel, name: tun}}]}}\n"
        "  - {id: F26E-0002, sysid: 2, links: "
        f"[{{uri: 'udp://127.0.0.1:{open_}', security: unsecured, name: open}}]}}\n"
        f"sinks:\n{sinks}routes:\n  - {{sinks: [{names}]}}\n"
    )
    return path


def metric(health: int, name: str, label: str) -> float:
    with urllib.request.urlopen(f"http://127.0.0.1:{health}/metrics", timeout=5) as response:
        text = response.read().decode()
    total = 0.0
    for line in text.splitlines():
        if line.startswith(name) and label in line:
            total += float(line.rsplit(" ", 1)[1])
    return total


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def churn(sources: int, ports: tuple[int, int]) -> None:
    for i in range(sources):
        address = f"127.{1 + i // 60000}.{(i // 250) % 240 + 1}.{i % 250 + 1}"
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.bind((address, 0))
            for port in ports:
                sock.sendto(GARBAGE, ("127.0.0.1", port))


def flood(port: int, rate: float, seconds: float, sent: multiprocessing.Value) -> None:  # type: ignore[type-arg]
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    batch = 100
    start = time.perf_counter()
    count = 0
    while time.perf_counter() - start < seconds:
        with contextlib.suppress(BlockingIOError):
            for _ in range(batch):
                sock.sendto(GARBAGE, ("127.0.0.1", port))
        count += batch
        ahead = count / rate - (time.perf_counter() - start)
        if ahead > 0:
            time.sleep(ahead)
    sent.value = count


def genuine(port: int, rate_hz: float, seconds: float) -> int:
    sealer = Sealer("F26E-0001", DayKeys(master=MASTER), lambda: datetime.now(UTC))
    m = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    count = 0
    start = time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        frame = m.global_position_int_encode(
            int(elapsed * 1000), 593_000_000, 181_000_000, 100_000, 90_000, 0, 0, 0, 0
        ).pack(m)
        sock.sendto(sealer.seal(bytes(frame)), ("127.0.0.1", port))
        count += 1
        time.sleep(max(0.0, count / rate_hz - (time.perf_counter() - start)))
    sock.close()
    return count


def delivery(
    health: int, port: int, args: argparse.Namespace, flood_rate: float
) -> dict[str, float]:
    before = metric(health, "fg_link_frames_total", 'link="tun"')
    garbage_before = metric(health, "fg_link_frames_rejected_total", 'link="tun"')
    sent_flood = multiprocessing.Value("q", 0)
    flooder = None
    if flood_rate:
        flooder = multiprocessing.Process(
            target=flood, args=(port, flood_rate, args.seconds + 1.0, sent_flood)
        )
        flooder.start()
        time.sleep(0.5)
    sent = genuine(port, args.genuine_rate, args.seconds)
    if flooder is not None:
        flooder.join()
    time.sleep(1.0)
    accepted = metric(health, "fg_link_frames_total", 'link="tun"') - before
    counted = metric(health, "fg_link_frames_rejected_total", 'link="tun"') - garbage_before
    return {
        "sent": sent,
        "accepted": accepted,
        "loss_pct": 100.0 * (1 - accepted / sent),
        "flood_sent_per_s": sent_flood.value / (args.seconds + 1.0),
        "flood_counted_per_s": counted / (args.seconds + 1.0),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sources", type=int, default=100_000)
    parser.add_argument("--flood-rate", type=float, default=100_000.0)
    parser.add_argument("--genuine-rate", type=float, default=200.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tun, open_ = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
        health = free_port(socket.SOCK_STREAM)
        config = write_config(Path(tmp), tun, open_, health)
        log = (Path(tmp) / "daemon.log").open("w")
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", "run", "--config", str(config)],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        try:
            deadline = time.monotonic() + 20
            while True:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{health}/readyz", timeout=1):
                        break
                except OSError:
                    if time.monotonic() > deadline or proc.poll() is not None:
                        raise SystemExit("the daemon did not become ready") from None
                    time.sleep(0.1)
            rss_start = rss_mb(proc.pid)
            started = time.perf_counter()
            churn(args.sources, (tun, open_))
            churn_s = time.perf_counter() - started
            time.sleep(2.0)
            rss_end = rss_mb(proc.pid)
            counted = metric(health, "fg_link_frames_rejected_total", "")
            quiet = delivery(health, tun, args, 0.0)
            flooded = delivery(health, tun, args, args.flood_rate)
            alive = proc.poll() is None
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=20)
            log.close()
    cpu = platform.processor() or platform.machine()
    print(
        f"Run on {platform.machine()} ({cpu}), {os.cpu_count()} cores, Python "
        f"{platform.python_version()}, {platform.system()} {platform.release()}, "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC: `python bench/attack.py "
        f"{' '.join(sys.argv[1:])}`\n"
    )
    title = "Garbage from distinct sources (one datagram each to a tunnel and an unsecured link)"
    print(f"**A. {title}.**\n")
    print("| sources | seconds | rejected counted | RSS before MB | RSS after MB | growth MB |")
    print("| --- | --- | --- | --- | --- | --- |")
    print(
        f"| {args.sources:,} | {churn_s:.1f} | {counted:,.0f} | {rss_start:.1f} | "
        f"{rss_end:.1f} | {rss_end - rss_start:+.1f} |\n"
    )
    print("**B. A genuine tunnel airframe under a garbage flood on its port.**\n")
    print("| flood offered /s | flood sent /s | flood read /s | genuine sent | accepted | loss % |")
    print("| --- | --- | --- | --- | --- | --- |")
    for rate, row in ((0.0, quiet), (args.flood_rate, flooded)):
        print(
            f"| {rate:,.0f} | {row['flood_sent_per_s']:,.0f} | {row['flood_counted_per_s']:,.0f} "
            f"| {row['sent']:,.0f} | {row['accepted']:,.0f} | {row['loss_pct']:.2f} |"
        )
    print(f"\nDaemon alive at the end: {alive}.")
    print(json.dumps({"quiet": quiet, "flooded": flooded}), file=sys.stderr)


if __name__ == "__main__":
    main()
