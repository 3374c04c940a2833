"""Mission geometry: the geofence's inside and crossing tests, route lengths (the
geodesic geometry itself: test_domain_fence.py)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.domain.geodesy import distance_bearing
from gateway.domain.mission import (
    crosses,
    inside,
    polygon_problem,
    route_inside,
    route_length_m,
)

SQUARE = [(65.0, 20.0), (65.0, 22.0), (66.0, 22.0), (66.0, 20.0)]
#: A U shape: the notch between its arms (65.3..66 N, 20.7..21.3 E) is outside.
U_FENCE = [
    (65.0, 20.0),
    (65.0, 22.0),
    (66.0, 22.0),
    (66.0, 21.3),
    (65.3, 21.3),
    (65.3, 20.7),
    (66.0, 20.7),
    (66.0, 20.0),
]


@given(
    st.floats(min_value=64.0, max_value=67.0, allow_nan=False),
    st.floats(min_value=19.0, max_value=23.0, allow_nan=False),
)
def test_inside_a_rectangle_is_inside_its_bounds(lat: float, lon: float) -> None:
    # Its east-west edges are geodesics, which bow up to 0.004° (0.4 km) north of the
    # parallels: further from them than that, the parallels decide.
    strictly_in = 65.005 < lat < 66.0 and 20.0 < lon < 22.0
    strictly_out = not (65.0 <= lat <= 66.005 and 20.0 <= lon <= 22.0)
    if strictly_in:
        assert inside(SQUARE, (lat, lon))
    elif strictly_out:
        assert not inside(SQUARE, (lat, lon))


def test_a_corner_and_an_edge_count_as_inside() -> None:
    assert inside(SQUARE, (65.0, 20.0))
    assert inside(SQUARE, (65.5, 22.0))


def test_the_notch_of_a_u_is_outside() -> None:
    assert not inside(U_FENCE, (65.8, 21.0))
    assert inside(U_FENCE, (65.8, 20.3))


def test_a_leg_across_the_notch_leaves_the_fence_between_two_inside_points() -> None:
    west, east = (65.8, 20.3), (65.8, 21.7)
    assert inside(U_FENCE, west)
    assert inside(U_FENCE, east)
    assert crosses(U_FENCE, west, east)
    assert route_inside(U_FENCE, [west, east]) == west
    assert route_inside(U_FENCE, [west, (65.1, 20.3), (65.1, 21.7), east]) is None


def test_the_first_point_outside_is_named() -> None:
    assert route_inside(SQUARE, [(65.5, 21.0), (64.5, 21.0), (63.0, 21.0)]) == (64.5, 21.0)


def test_a_fence_needs_three_corners() -> None:
    with pytest.raises(ValueError, match="at least 3 corners"):
        inside(SQUARE[:2], (65.5, 21.0))


def test_route_length_is_the_sum_of_geodesic_legs() -> None:
    points = [(65.0, 20.0), (65.0, 21.0), (66.0, 21.0)]
    legs = distance_bearing(65.0, 20.0, 65.0, 21.0)[0] + distance_bearing(65.0, 21.0, 66.0, 21.0)[0]
    assert route_length_m(points) == pytest.approx(legs)
    assert route_length_m(points[:1]) == 0.0


def test_a_fence_across_the_antimeridian_is_not_turned_inside_out() -> None:
    fence = [(65.0, 179.0), (65.0, -179.0), (66.0, -179.0), (66.0, 179.0)]
    assert inside(fence, (65.5, 179.5))
    assert inside(fence, (65.5, -179.5))
    assert inside(fence, (65.5, 180.0))
    assert not inside(fence, (65.5, 0.0))
    assert not inside(fence, (65.5, 178.0))
    assert route_inside(fence, [(65.5, 179.5), (65.5, -179.5)]) is None


def test_polygon_problems_are_named_with_their_corners() -> None:
    square = [(65.8, 21.0), (65.8, 21.1), (65.9, 21.1), (65.9, 21.0)]
    assert polygon_problem(square) is None
    bow_tie = [(65.8, 21.0), (65.9, 21.1), (65.9, 21.0), (65.8, 21.1)]
    assert polygon_problem(bow_tie) == "crosses itself: edge 1-2 crosses edge 3-4"
    repeated = [(65.8, 21.0), (65.8, 21.0), (65.9, 21.1)]
    assert polygon_problem(repeated) == "has corners 1 and 2 at the same point"
    line = [(65.8, 21.0), (65.85, 21.0), (65.9, 21.0)]
    assert polygon_problem(line) == "has no area (its corners are on one line)"
    across = [(65.0, 179.9), (65.0, -179.9), (66.0, -179.9), (66.0, 179.9)]
    assert polygon_problem(across) is None
