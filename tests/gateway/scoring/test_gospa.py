"""GOSPA and its assignment: known values by hand, and the assignment against SciPy's."""

from __future__ import annotations

import math
import random

import pytest
from scipy.optimize import linear_sum_assignment  # with Stone Soup, in the test extra

from gateway.scoring.gospa import assign, gospa

C, P = 100.0, 2.0
HALF = C**P / 2  # one missed or one false target


class TestGospa:
    """GOSPA (c = 100 m, p = 2, α = 2) on sets small enough to check by hand."""

    def test_empty_sets_are_zero(self) -> None:
        assert gospa([], [], C, P).distance == 0.0

    def test_a_missed_target_costs_c_over_root_2(self) -> None:
        frame = gospa([(0.0, 0.0)], [], C, P)
        assert frame.distance == pytest.approx(math.sqrt(HALF))
        assert (frame.missed, frame.false, frame.pairs) == (HALF, 0.0, ())

    def test_a_close_pair_costs_its_distance(self) -> None:
        frame = gospa([(0.0, 0.0)], [(3.0, 4.0)], C, P)
        assert frame.distance == pytest.approx(5.0)
        assert frame.pairs == ((0, 0),)

    def test_a_pair_beyond_c_is_one_miss_and_one_false(self) -> None:
        frame = gospa([(0.0, 0.0)], [(150.0, 0.0)], C, P)
        assert frame.distance == pytest.approx(C)
        assert (frame.missed, frame.false, frame.pairs) == (HALF, HALF, ())

    def test_a_duplicate_track_is_false(self) -> None:
        frame = gospa([(0.0, 0.0)], [(6.0, 8.0), (3.0, 4.0)], C, P)
        assert frame.distance == pytest.approx(math.sqrt(25.0 + HALF))
        assert frame.pairs == ((0, 1),)

    def test_the_assignment_is_optimal_not_greedy(self) -> None:
        # Greedy would pair truth 0 with the estimate at x=1 (distance 1) and leave truth 1
        # 99 m from the other; the optimum crosses over: 9 + 9.
        truth = [(0.0, 0.0), (10.0, 0.0)]
        estimates = [(1.0, 0.0), (-9.0, 0.0)]
        frame = gospa(truth, estimates, C, P)
        assert frame.distance == pytest.approx(math.sqrt(9.0**2 + 9.0**2))
        assert frame.pairs == ((0, 1), (1, 0))

    def test_more_truth_than_estimates(self) -> None:
        frame = gospa([(0.0, 0.0), (500.0, 0.0), (0.0, 500.0)], [(0.0, 2.0)], C, P)
        assert frame.distance == pytest.approx(math.sqrt(4.0 + 2 * HALF))
        assert frame.pairs == ((0, 0),)

    @pytest.mark.parametrize(("c", "p"), [(0.0, 2.0), (100.0, 0.5), (-1.0, 1.0)])
    def test_bad_parameters_are_refused(self, c: float, p: float) -> None:
        with pytest.raises(ValueError, match="expected c > 0 and p >= 1"):
            gospa([(0.0, 0.0)], [], c, p)


class TestAssign:
    """The assignment is an optimum, every row with its own column."""

    def test_matches_scipy_on_random_matrices(self) -> None:
        rng = random.Random(22)
        for _ in range(300):
            n = rng.randint(1, 7)
            m = rng.randint(n, 9)
            cost = [
                [rng.choice([rng.random() * 100, 5.0, 50.0]) for _ in range(m)] for _ in range(n)
            ]
            columns = assign(cost)
            assert len(set(columns)) == n
            rows, cols = linear_sum_assignment(cost)
            best = sum(cost[r][c] for r, c in zip(rows, cols, strict=True))
            assert sum(cost[i][j] for i, j in enumerate(columns)) == pytest.approx(best)

    def test_more_rows_than_columns_is_refused(self) -> None:
        with pytest.raises(ValueError, match="rows <= columns"):
            assign([[1.0], [2.0]])
