"""``fischer-gateway selftest``: compute every claim of the ledger and report on each.

The report lists every claim with its identifier, the computed value, the expected value and
tolerance, the formula and inputs, and any caveat noted in the ledger, then a summary line.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping
from typing import TextIO

from gateway.domain.claims import ClaimResult, Value, evaluate, load_claims

__all__ = ["format_value", "run_selftest"]

_INDENT = " " * 6


def format_value(value: Value | None, tolerance: float | None = None) -> str:
    """A value as the report shows it: True/False, the text, or the number to six
    significant digits, or, given its ``tolerance`` (half a unit in the last digit), to
    the digits its source stated (expected 34.0 ± 0.05 shows as ``34.0``).
    """
    if value is None:
        return "—"
    if isinstance(value, bool | str):
        return str(value)
    if tolerance:
        decimals = max(0, -math.floor(math.log10(2 * tolerance) + 1e-9))
        return f"{value:,.{decimals}f}"
    return f"{value:,.6g}"


def _input(value: object) -> str:
    if isinstance(value, float):
        return format_value(value)
    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{k}: {_input(v)}" for k, v in value.items()) + "}"
    return str(value)


def _inputs(inputs: Mapping[str, object]) -> str:
    if not inputs:
        return "the EnergyProfile defaults"
    return ", ".join(f"{key}={_input(value)}" for key, value in inputs.items())


def _wrap(text: str) -> list[str]:
    return textwrap.wrap(text, 100, initial_indent=_INDENT, subsequent_indent=_INDENT + "  ")


def _entry(result: ClaimResult, width: int) -> list[str]:
    claim = result.claim
    mark = "PASS" if result.ok else "FAIL"
    expected = format_value(claim.expected, claim.tolerance)
    if not isinstance(claim.expected, bool | str):
        expected += f" ± {format_value(claim.tolerance)}"
    lines = [
        f"{mark}  {claim.id:<{width}}  {format_value(result.value):>16} {claim.unit:<6}"
        f"  expected {expected}",
        *_wrap(claim.what),
        *_wrap(f"= {claim.formula}"),
        *_wrap(f"inputs: {_inputs(claim.inputs)}"),
        *_wrap(f"source: {claim.source}"),
    ]
    if result.error is not None:
        lines += _wrap(f"error: {result.error}")
    if claim.notes:
        lines += _wrap(f"note: {claim.notes}")
    return lines


def run_selftest(stream: TextIO) -> int:
    """Write the claims report to ``stream``; return 0 if every claim holds, else 1."""
    results = [evaluate(claim) for claim in load_claims()]
    width = max(len(r.claim.id) for r in results)
    stream.write(
        f"fischer-gateway self-test: {len(results)} claims, each computed by gateway.domain\n\n"
    )
    for result in results:
        stream.write("\n".join(_entry(result, width)) + "\n")
    failed = [r.claim.id for r in results if not r.ok]
    stream.write(f"\n{len(results) - len(failed)}/{len(results)} claims hold\n")
    if failed:
        stream.write(f"FAILED: {', '.join(failed)}\n")
    return 1 if failed else 0
