"""The spatial hash grid: exact radius queries, kept exact through inserts, moves and removals."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.flow.gridindex import GridIndex


class TestGridIndex:
    """Keys filed by position; ``within`` answers as a brute-force scan would."""

    def test_within_finds_only_keys_inside_the_radius(self) -> None:
        grid: GridIndex[str] = GridIndex(100.0)
        grid.insert("a", 0.0, 0.0)
        grid.insert("b", 150.0, 0.0)
        grid.insert("c", -99.0, -1.0)
        assert sorted(grid.within(0.0, 0.0, 100.0)) == ["a", "c"]
        assert sorted(grid.within(0.0, 0.0, 150.0)) == ["a", "b", "c"]
        assert grid.within(1000.0, 1000.0, 10.0) == []

    def test_boundary_distance_is_inside(self) -> None:
        grid: GridIndex[int] = GridIndex(10.0)
        grid.insert(1, 30.0, 40.0)
        assert grid.within(0.0, 0.0, 50.0) == [1]

    def test_move_and_remove_refile_the_key(self) -> None:
        grid: GridIndex[str] = GridIndex(50.0)
        grid.insert("a", 0.0, 0.0)
        grid.move("a", 500.0, 500.0)
        assert grid.within(0.0, 0.0, 10.0) == []
        assert grid.within(500.0, 500.0, 1.0) == ["a"]
        assert grid.position("a") == (500.0, 500.0)
        grid.remove("a")
        assert len(grid) == 0
        assert "a" not in grid
        assert grid.within(500.0, 500.0, 1.0) == []

    def test_misuse_raises_key_error(self) -> None:
        grid: GridIndex[str] = GridIndex(50.0)
        grid.insert("a", 0.0, 0.0)
        with pytest.raises(KeyError):
            grid.insert("a", 1.0, 1.0)
        with pytest.raises(KeyError):
            grid.move("b", 1.0, 1.0)
        with pytest.raises(KeyError):
            grid.remove("b")

    @pytest.mark.parametrize("cell", [0.0, -1.0, math.inf, math.nan])
    def test_cell_size_must_be_positive_and_finite(self, cell: float) -> None:
        with pytest.raises(ValueError, match="cell_m"):
            GridIndex(cell)

    def test_a_huge_radius_walks_the_occupied_cells(self) -> None:
        grid: GridIndex[int] = GridIndex(1.0)
        for i in range(10):
            grid.insert(i, i * 1000.0, -i * 1000.0)
        assert sorted(grid.within(0.0, 0.0, 1e9)) == list(range(10))


coordinate = st.floats(min_value=-5000.0, max_value=5000.0, allow_nan=False)
operation = st.tuples(
    st.sampled_from(["insert", "move", "remove"]),
    st.integers(min_value=0, max_value=15),
    coordinate,
    coordinate,
)


@settings(max_examples=150, deadline=None)
@given(
    cell=st.floats(min_value=1.0, max_value=2000.0),
    operations=st.lists(operation, max_size=60),
    queries=st.lists(
        st.tuples(coordinate, coordinate, st.floats(min_value=0.0, max_value=8000.0)),
        min_size=1,
        max_size=8,
    ),
)
def test_within_agrees_with_brute_force(
    cell: float,
    operations: list[tuple[str, int, float, float]],
    queries: list[tuple[float, float, float]],
) -> None:
    """Any sequence of inserts, moves and removals; every query equals a scan of all keys."""
    grid: GridIndex[int] = GridIndex(cell)
    truth: dict[int, tuple[float, float]] = {}
    for op, key, x, y in operations:
        if op == "insert" and key not in truth:
            grid.insert(key, x, y)
            truth[key] = (x, y)
        elif op == "move" and key in truth:
            grid.move(key, x, y)
            truth[key] = (x, y)
        elif op == "remove" and key in truth:
            grid.remove(key)
            del truth[key]
    assert len(grid) == len(truth)
    for qx, qy, radius in queries:
        expected = {k for k, (x, y) in truth.items() if math.hypot(x - qx, y - qy) <= radius}
        assert sorted(grid.within(qx, qy, radius)) == sorted(expected)
