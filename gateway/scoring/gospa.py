"""GOSPA between two point sets in a plane, and the optimal assignment under it.

The generalised optimal sub-pattern assignment metric (Rahmathullah, García-Fernández and
Svensson, 2017) with α = 2: for truth points X, estimates Y, cutoff c and order p,

    GOSPA(X, Y)^p = min over assignments γ  Σ_(i,j)∈γ d(x_i, y_j)^p  +  c^p / 2 · (|X| + |Y| − 2|γ|)

over pairs closer than c. Computed as the minimum-cost assignment of the smaller set into the
larger on the costs min(d, c)^p, plus c^p / 2 for every point of the larger set left over: a
pair at c or farther costs c^p, the same as one miss and one false estimate.

``assign`` is the Hungarian algorithm with potentials (O(n²m)), in pure Python so the
gateway needs no numerical library; the tests check it against SciPy and the whole metric
against Stone Soup's ``GOSPAMetric``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

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
    u = [0.0] * (n + 1)
    v = [0.0] * (m + 1)
    owner = [0] * (m + 1)  # owner[j]: the row (1-based) holding column j; 0 for none
    way = [0] * (m + 1)
    for i in range(1, n + 1):
        owner[0] = i
        j0 = 0
        best = [math.inf] * (m + 1)
        used = [False] * (m + 1)
        while True:
            used[j0] = True
            i0 = owner[j0]
            row = cost[i0 - 1]
            delta, j1 = math.inf, 0
            for j in range(1, m + 1):
                if used[j]:
                    continue
                reduced = row[j - 1] - u[i0] - v[j]
                if reduced < best[j]:
                    best[j], way[j] = reduced, j0
                if best[j] < delta:
                    delta, j1 = best[j], j
            for j in range(m + 1):
                if used[j]:
                    u[owner[j]] += delta
                    v[j] -= delta
                else:
                    best[j] -= delta
            j0 = j1
            if owner[j0] == 0:
                break
        while j0:
            j1 = way[j0]
            owner[j0] = owner[j1]
            j0 = j1
    result = [-1] * n
    for j in range(1, m + 1):
        if owner[j]:
            result[owner[j] - 1] = j - 1
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
