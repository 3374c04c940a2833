"""A/B: this tree's ingest pipeline against another commit's, interleaved in one run.

Reproducible: ``python bench/ab.py --before REF`` (a commit, tag or branch; default the
merge-base with ``origin/main`` is not guessed: give it). It checks REF out into a temporary
git worktree, then for ``--rounds`` rounds (5 by default) runs, alternately in each tree and in
a fresh process each, ``bench/ingest.py``'s part A (the pipeline on one core: the same
datagrams through a bare pymavlink parse loop and through the gateway's ingest → normalise →
bus → five sinks, in one process). Each run yields the gateway's messages/s ÷ pymavlink's on
the same datagrams in the same process: a CPU-time ratio that a shared machine's load cancels
out of. Prints the median, min and max of each tree's ratios per condition and after ÷ before.
The other tree runs with this interpreter and its packages, its own code first on the path.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GIT = shutil.which("git") or "git"

#: Runs part A of the tree's own bench/ingest.py for one condition; prints the ratio.
PROBE = """
import sys, tempfile
from pathlib import Path
sys.path.insert(0, "bench")
import ingest
from gateway.ops.logsetup import configure_logging
configure_logging("warning", sys.stderr)
n, tunnel = int(sys.argv[1]), sys.argv[2] == "on"
key = Path(tempfile.mkdtemp()) / "master.key"
key.write_text(ingest.MASTER.hex())
key.chmod(0o600)
datagrams = ingest.make_datagrams(n, max(1.0, 40_000 / (n * 13)), tunnel)
bare = ingest.bare_pymavlink(datagrams, tunnel)
ours = ingest.gateway_pipeline(datagrams, n, tunnel, str(key))
print(ours / bare)
"""


def ratio(tree: Path, airframes: int, tunnel: bool) -> float:
    """One fresh process in ``tree``: the gateway's rate ÷ pymavlink's."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run(
        [sys.executable, "-c", PROBE, str(airframes), "on" if tunnel else "off"],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return float(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", required=True, help="the commit to compare against")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--airframes", default="1,100")
    args = parser.parse_args(argv)
    conditions = [(int(n), t) for n in args.airframes.split(",") for t in (False, True)]
    with tempfile.TemporaryDirectory(prefix="fischer-ab-") as tmp:
        before = Path(tmp) / "before"
        subprocess.run(
            [GIT, "worktree", "add", "--detach", "-q", str(before), args.before],
            cwd=ROOT,
            check=True,
        )
        try:
            got: dict[tuple[str, int, bool], list[float]] = {}
            for _ in range(args.rounds):
                for n, tunnel in conditions:
                    for label, tree in (("before", before), ("after", ROOT)):
                        got.setdefault((label, n, tunnel), []).append(ratio(tree, n, tunnel))
        finally:
            subprocess.run([GIT, "worktree", "remove", "--force", str(before)], cwd=ROOT)
    head = subprocess.run(
        [GIT, "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    print(f"A/B of the ingest pipeline, {args.rounds} interleaved rounds: {args.before} → {head}")
    print("| airframes | tunnel | before: median (min-max) | after: median (min-max) | ratio |")
    print("| --- | --- | --- | --- | --- |")
    for n, tunnel in conditions:
        b, a = got[("before", n, tunnel)], got[("after", n, tunnel)]
        mb, ma = statistics.median(b), statistics.median(a)
        print(
            f"| {n} | {'on' if tunnel else 'off'} | {mb:.3f} ({min(b):.3f}-{max(b):.3f}) "
            f"| {ma:.3f} ({min(a):.3f}-{max(a):.3f}) | {ma / mb:.3f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
