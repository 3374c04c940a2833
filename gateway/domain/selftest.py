"""``fischer-gateway selftest``: compute every claim of the ledger and report."""

from __future__ import annotations

from typing import TextIO

from gateway.domain.claims import evaluate, load_claims

__all__ = ["run_selftest"]


def _fmt(value: float) -> str:
    return f"{value:,.4f}".rstrip("0").rstrip(".") if value != int(value) else f"{int(value):,}"


def run_selftest(stream: TextIO) -> int:
    """Print the claims report to ``stream``; return 0 if every claim holds, else 1."""
    results = [evaluate(claim) for claim in load_claims()]
    width = max(len(r.claim.id) for r in results)
    stream.write("fischer-gateway self-test: every figure computed by the SDK\n\n")
    for result in results:
        claim = result.claim
        mark = "PASS" if result.ok else "FAIL"
        stream.write(
            f"[{mark}] {claim.id:<{width}}  {_fmt(result.value):>10} {claim.unit:<6}"
            f" expected {_fmt(claim.expected)} ± {_fmt(claim.tolerance)}\n"
            f"       {claim.what}: {claim.formula}\n"
        )
    failed = [r for r in results if not r.ok]
    stream.write(f"\n{len(results) - len(failed)}/{len(results)} claims hold\n")
    return 1 if failed else 0
