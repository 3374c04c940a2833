"""The joint assignment: its shortcuts give matchings as good as a full solve."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linear_sum_assignment

from tracking.assign import assign

costs = st.floats(min_value=-20.0, max_value=40.0, allow_nan=False)
pairs_st = st.dictionaries(
    st.tuples(st.integers(0, 5), st.integers(0, 5)), costs, min_size=0, max_size=24
)


def _reference(pairs: dict[tuple[int, int], float]) -> tuple[int, float]:
    """(pairs matched, total cost) of an optimal matching: most pairs, then least cost."""
    if not pairs:
        return 0, 0.0
    rows = sorted({r for r, _ in pairs})
    cols = sorted({c for _, c in pairs})
    big = 1e7
    matrix = np.full((len(rows), len(cols)), big)
    for (r, c), cost in pairs.items():
        matrix[rows.index(r), cols.index(c)] = cost - 1e5
    chosen = [
        (rows[i], cols[j])
        for i, j in zip(*linear_sum_assignment(matrix), strict=True)
        if matrix[i, j] < big
    ]
    return len(chosen), sum(pairs[p] for p in chosen)


@settings(max_examples=300, deadline=None)
@given(pairs=pairs_st)
def test_assign_is_one_to_one_over_given_pairs_and_optimal(
    pairs: dict[tuple[int, int], float],
) -> None:
    matched = assign(pairs)
    assert len(set(matched.values())) == len(matched)  # one to one
    assert all((r, c) in pairs for r, c in matched.items())  # only gated pairs
    count, total = _reference(pairs)
    assert len(matched) == count
    assert abs(sum(pairs[(r, c)] for r, c in matched.items()) - total) < 1e-6


def test_a_contested_track_goes_to_the_matching_that_is_best_overall() -> None:
    # Both detections are nearest track 0; detection 1 alone can also take track 1.
    pairs = {(0, 0): 1.0, (1, 0): 0.5, (1, 1): 3.0}
    assert assign(pairs) == {0: 0, 1: 1}
    # Each detection's cheapest track is its own: taken as is.
    assert assign({(0, 0): 1.0, (0, 1): 9.0, (1, 1): 2.0, (1, 0): 8.0}) == {0: 0, 1: 1}
