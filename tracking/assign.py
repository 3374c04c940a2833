"""Global nearest neighbour: the joint assignment of one sensor frame's detections to tracks.

A sensor frame (one airframe, one sensor, one time) sees each object at most once, so its
detections and the tracks they gate with are matched one to one, all at once. ``assign``
takes the gated pairs with their costs (d² + ln det S: the negative log-likelihood of the
pair, up to a constant) and returns the matching that first pairs as many detections as can
be paired, then has the least total cost. Pairs not given are not allowed (outside the gate,
or in total class conflict). Ties are broken by the order of rows and columns, which the
tracker fixes canonically, so the outcome never depends on the order detections arrived in.

When every detection's cheapest track is a different track, that is the answer. Otherwise it
is solved on each connected group of the gated pairs: one detection or one track by the cheapest
pair, up to three detections against up to three tracks by trying every matching (faster than
a call into scipy for such a group), larger ones by ``scipy.optimize.linear_sum_assignment``.
"""

from __future__ import annotations

from collections.abc import Mapping
from itertools import product

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["assign"]

#: Cost of a pair not allowed: larger than any sum of real costs, so never chosen when a
#: matching without it pairs as many detections.
_FORBIDDEN = 1e9
#: Added to every allowed cost before solving, so a matching with more pairs always wins.
_PAIRED_BONUS = 1e6
#: Groups with at most this many detections and tracks are solved by trying every matching.
_SMALL = 3


def _exhaustive(
    rows: list[int], cols: list[int], pairs: Mapping[tuple[int, int], float]
) -> dict[int, int]:
    """The best matching of a small group by enumeration: most pairs, then least cost; the
    first found in row-major order of the choices wins a tie."""
    options = [[None, *(c for c in cols if (r, c) in pairs)] for r in rows]
    best: tuple[int, float] | None = None
    chosen: tuple[int | None, ...] = ()
    for choice in product(*options):
        taken = [c for c in choice if c is not None]
        if len(taken) != len(set(taken)):
            continue
        cost = sum(pairs[(r, c)] for r, c in zip(rows, choice, strict=True) if c is not None)
        rank = (-len(taken), cost)
        if best is None or rank < best:
            best, chosen = rank, choice
    return {r: c for r, c in zip(rows, chosen, strict=True) if c is not None}


def _groups(pairs: Mapping[tuple[int, int], float]) -> list[tuple[list[int], list[int]]]:
    """Connected components of the bipartite gate graph, as (rows, columns), sorted."""
    parent: dict[tuple[str, int], tuple[str, int]] = {}

    def find(node: tuple[str, int]) -> tuple[str, int]:
        root = node
        while parent.setdefault(root, root) != root:
            root = parent[root]
        while parent[node] != root:
            parent[node], node = root, parent[node]
        return root

    for row, col in pairs:
        a, b = find(("r", row)), find(("c", col))
        if a != b:
            parent[max(a, b)] = min(a, b)
    members: dict[tuple[str, int], tuple[list[int], list[int]]] = {}
    for node in list(parent):
        rows, cols = members.setdefault(find(node), ([], []))
        (rows if node[0] == "r" else cols).append(node[1])
    return [(sorted(rows), sorted(cols)) for rows, cols in members.values()]


def _each_to_its_best(pairs: Mapping[tuple[int, int], float]) -> dict[int, int] | None:
    """Every row's cheapest column, when no two rows share one (then that matching pairs every
    row at the least cost each row could have: it is optimal); else None."""
    best: dict[int, tuple[float, int]] = {}
    for (row, col), cost in pairs.items():
        held = best.get(row)
        if held is None or (cost, col) < held:
            best[row] = (cost, col)
    chosen = {row: col for row, (_, col) in best.items()}
    return chosen if len(set(chosen.values())) == len(chosen) else None


def assign(pairs: Mapping[tuple[int, int], float]) -> dict[int, int]:
    """Row (detection) → column (track) for the best one-to-one matching of ``pairs``."""
    easy = _each_to_its_best(pairs)
    if easy is not None:
        return easy  # the usual frame: detections of objects far apart in their gates' terms
    out: dict[int, int] = {}
    for rows, cols in _groups(pairs):
        if len(rows) == 1 or len(cols) == 1:
            # One detection, or one track: the cheapest pair is the whole answer.
            row, col = min(
                ((r, c) for r in rows for c in cols if (r, c) in pairs),
                key=lambda rc: (pairs[rc], rc),
            )
            out[row] = col
            continue
        if len(rows) <= _SMALL and len(cols) <= _SMALL:
            out.update(_exhaustive(rows, cols, pairs))
            continue
        matrix = np.full((len(rows), len(cols)), _FORBIDDEN)
        for i, row in enumerate(rows):
            for j, col in enumerate(cols):
                cost = pairs.get((row, col))
                if cost is not None:
                    matrix[i, j] = cost - _PAIRED_BONUS
        chosen_rows, chosen_cols = linear_sum_assignment(matrix)
        for i, j in zip(chosen_rows.tolist(), chosen_cols.tolist(), strict=True):
            if matrix[i, j] < _FORBIDDEN:
                out[rows[i]] = cols[j]
    return out
