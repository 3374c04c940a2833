"""GOSPA between two point sets in a plane, and the optimal assignment under it.

The generalised optimal sub-pattern assignment metric (Rahmathullah, García-Fernández and
Svensson, 2017) with α = 2: for truth points X, estimates Y, cutoff c and order p,

    GOSPA(X, Y)^p = min over assignments γ  Σ_(i,j)∈γ d(x_i, y_j)^p  +  c^p / 2 · (|X| + |Y| − 2|γ|)

over pairs closer than c. Computed as the minimum-cost assignment of the smaller set into the
larger on the costs min(d, c)^p, plus c^p / 2 for every point of the larger set left over: a
pair at c or farther costs c^p, the same as one miss and one false estimate.

``assign`` is SciPy's ``linear_sum_assignment`` (the tracker's too); the tests check the
whole metric against Stone Soup's ``GOSPAMetric``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from scipy.optimize import linear_sum_assignment

__all__ = ["GospaFrame", "assign", "gospa"]

Point = tuple[float, float]


def assign(cost: Sequence[Sequence[float]]) -> list[int]:
    """The column given to each row in a minimum-cost assignment (rows ≤ columns).

    Every row gets a distinct column. Raises ``ValueError`` when there are more rows than
    columns or the rows differ in length.
    """
    n = len(cost)
    if n == 0:
        return []
    m = len(cost[0])
    if any(len(row) != m for row in cost) or n > m:
        raise ValueError(f"expected rows of equal length and rows <= columns, got {n} x {m}")
    rows, columns = linear_sum_assignment(cost)
    result = [-1] * n
    for row, column in zip(rows, columns, strict=True):
        result[int(row)] = int(column)
    return result


@dataclass(frozen=True, slots=True)
class GospaFrame:
    """GOSPA at one instant and how it splits (the three terms are p-th powers)."""

    distance: float
    localisation: float
    missed: float
    false: float
    #: (truth index, estimate index) of every pair closer than c.
    pairs: tuple[tuple[int, int], ...]


def gospa(truth: Sequence[Point], estimates: Sequence[Point], c: float, p: float) -> GospaFrame:
    """GOSPA (α = 2) between ``truth`` and ``estimates``, Euclidean in the plane."""
    if not (c > 0 and p >= 1):
        raise ValueError(f"expected c > 0 and p >= 1, got c={c!r} p={p!r}")
    cp = c**p
    dummy = cp / 2
    if not truth or not estimates:
        return GospaFrame(
            distance=(dummy * (len(truth) + len(estimates))) ** (1 / p),
            localisation=0.0,
            missed=dummy * len(truth),
            false=dummy * len(estimates),
            pairs=(),
        )
    flipped = len(truth) > len(estimates)
    rows, cols = (estimates, truth) if flipped else (truth, estimates)
    cost = [[min(math.dist(r, k), c) ** p for k in cols] for r in rows]
    columns = assign(cost)
    pairs = []
    localisation = 0.0
    for i, j in enumerate(columns):
        if cost[i][j] < cp:
            localisation += cost[i][j]
            pairs.append((j, i) if flipped else (i, j))
    matched = len(pairs)
    missed = dummy * (len(truth) - matched)
    false = dummy * (len(estimates) - matched)
    return GospaFrame(
        distance=(localisation + missed + false) ** (1 / p),
        localisation=localisation,
        missed=missed,
        false=false,
        pairs=tuple(sorted(pairs)),
    )
