"""One HTTPS POST as the ``gute2`` and ``slb`` sinks make it: client CPU time and latency.

Reproducible: ``python bench/httpspost.py`` (``--compare TREE`` also runs the client of
another source tree, interleaved, in the same run). Prints a Markdown table.

- The **client** is ``gateway.transports.httpspost.HttpsPoster`` of a tree, in a process of its
  own, POSTing ``--posts`` handoff documents one after another (as the runner of one ``gute2``
  sink does: one cue per batch) with ``max_in_flight`` 4.
- The **server** is the tests' HTTPS battery (``tests/https_peer.py``: loopback, its own CA,
  client certificates required, HTTP/1.1 keep-alive) in another process; it answers 201.
- Measured in the client: the CPU time of the process per POST (``time.process_time``: what a
  POST costs the gateway's one event loop, stable on a shared machine) and the wall time of
  each POST, p50 / p90. The first ``--warm-up`` POSTs (the TLS handshake) are not counted.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent / "tests"


def serve(directory: Path) -> None:
    """Run the battery until stdin closes; print its port and TLS files as one JSON line."""
    import anyio
    from anyio.to_thread import run_sync

    sys.path.insert(0, str(TESTS))
    from https_peer import Answer, Head, HttpsPeer

    class Battery(HttpsPeer):
        def _answer(self, head: Head, body: bytes) -> Answer:
            self.requests.clear()  # keep nothing: a long run stays small
            return 201, {"status": "accepted"}

    async def main() -> None:
        async with Battery(directory, file_prefix="bench") as peer:
            print(json.dumps({"port": peer.port, **peer.tls_options()}), flush=True)
            await run_sync(sys.stdin.read)

    anyio.run(main, backend="asyncio")


def client(url: str, tls: dict[str, str], posts: int, warm_up: int) -> None:
    """POST ``posts`` documents one after another; print the figures as one JSON line."""
    import anyio

    from gateway.contract import sample_events
    from gateway.events import EventKind
    from gateway.transports.httpspost import HttpsPoster
    from gateway.transports.tls import TlsFiles
    from sinks.gute2.codec import encode_handoff

    sample = sample_events(frozenset({EventKind.HANDOFF}))[0]
    files = TlsFiles(Path(tls["ca_file"]), Path(tls["cert_file"]), Path(tls["key_file"]))

    async def main() -> dict[str, Any]:
        poster = HttpsPoster("bench", url, files, timeout_s=5.0, max_in_flight=4)
        events = [
            sample.model_copy(update={"event_id": f"HO-{n}", "handoff_id": f"HO-{n}"})
            for n in range(posts + warm_up)
        ]
        walls: list[float] = []
        failed = 0
        try:
            for event in events[:warm_up]:
                await poster.post_all([event], encode_handoff)
            cpu = time.process_time()
            for event in events[warm_up:]:
                start = time.perf_counter()
                (outcome,) = await poster.post_all([event], encode_handoff)
                walls.append(time.perf_counter() - start)
                failed += outcome.result != "delivered"
            cpu = time.process_time() - cpu
        finally:
            await poster.aclose()
        walls.sort()
        return {
            "cpu_us": cpu / posts * 1e6,
            "p50_ms": walls[len(walls) // 2] * 1e3,
            "p90_ms": walls[int(len(walls) * 0.9)] * 1e3,
            "failed": failed,
        }

    try:
        import uvloop

        options: dict[str, Any] = {"use_uvloop": True}
        del uvloop
    except ImportError:
        options = {}
    print(json.dumps(anyio.run(main, backend="asyncio", backend_options=options)), flush=True)


def spread(values: list[float], fmt: str = "{:.2f}") -> str:
    """min / median / max over the rounds."""
    return " / ".join(fmt.format(v) for v in (min(values), statistics.median(values), max(values)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--posts", type=int, default=500, help="POSTs measured per round")
    parser.add_argument("--warm-up", type=int, default=20, help="POSTs not counted")
    parser.add_argument("--compare", type=Path, help="also run the client of this tree")
    parser.add_argument("--serve", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--client", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        serve(args.serve)
        return
    if args.client:
        url, tls = json.loads(args.client)
        client(url, tls, args.posts, args.warm_up)
        return
    directory = Path(tempfile.mkdtemp(prefix="fg-httpspost-"))
    server = subprocess.Popen(
        [sys.executable, __file__, "--serve", str(directory)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert server.stdout is not None
    started = json.loads(server.stdout.readline())
    url = f"https://127.0.0.1:{started.pop('port')}/gute2/handoffs"
    trees: list[tuple[str, Path]] = [("this tree", HERE.parent)]
    if args.compare:
        trees.append((str(args.compare), args.compare.resolve()))
    rows: dict[str, dict[str, list[float]]] = {name: {} for name, _ in trees}
    try:
        for _ in range(args.rounds):
            for name, tree in trees:
                done = subprocess.run(
                    [
                        sys.executable,
                        __file__,
                        "--client",
                        json.dumps([url, started]),
                        "--posts",
                        str(args.posts),
                        "--warm-up",
                        str(args.warm_up),
                    ],
                    env={**os.environ, "PYTHONPATH": str(tree)},
                    cwd=tree,
                    capture_output=True,
                    text=True,
                    check=True,
                )
                figures = json.loads(done.stdout.strip().splitlines()[-1])
                print(f"  {name}: {figures}", file=sys.stderr)
                for key, value in figures.items():
                    rows[name].setdefault(key, []).append(value)
    finally:
        server.stdin.close()  # type: ignore[union-attr]
        server.wait(timeout=10)
    print(f"# one HTTPS POST (HttpsPoster), {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}; load average {os.getloadavg()[0]:.1f}"
    )
    print(
        f"command: python bench/httpspost.py --rounds {args.rounds} --posts {args.posts}; "
        "min / median / max of the rounds\n"
    )
    print("| client | CPU µs per POST | p50 ms | p90 ms | failed |")
    print("| --- | --- | --- | --- | --- |")
    for name, _ in trees:
        f = rows[name]
        print(
            f"| {name} | {spread(f['cpu_us'], '{:.0f}')} | {spread(f['p50_ms'])} "
            f"| {spread(f['p90_ms'])} | {spread(f['failed'], '{:.0f}')} |"
        )
    if args.compare:
        mine, theirs = rows[trees[0][0]]["cpu_us"], rows[trees[1][0]]["cpu_us"]
        ratios = [a / b for a, b in zip(mine, theirs, strict=True)]
        print(f"\nCPU per POST, this tree ÷ {trees[1][0]} (per round): {spread(ratios)}")


if __name__ == "__main__":
    main()
