"""Camera pointing between frames, and the optical axis on the ground (domain/lookat.py)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.domain.geodesy import distance_bearing
from gateway.domain.lookat import (
    MIN_STEP_M,
    absolute_pointing,
    flat_intersection,
    footprint_width_m,
    ground_intersection,
    quaternion_to_euler,
    relative_pointing,
)

angles = st.floats(-math.pi / 2 + 0.01, math.pi / 2 - 0.01)


def flat(_lat: float, _lon: float) -> float | None:
    return None


@given(angles, angles, st.floats(-math.pi, math.pi), st.floats(0, 359.9), st.floats(-85, 85))
def test_relative_then_absolute_is_the_identity(
    roll: float, pitch: float, yaw: float, azimuth: float, elevation: float
) -> None:
    rel = relative_pointing(roll, pitch, yaw, azimuth, elevation)
    back = absolute_pointing(roll, pitch, yaw, *rel)
    assert back[1] == pytest.approx(elevation, abs=1e-6)
    assert math.cos(math.radians(back[0] - azimuth)) == pytest.approx(1.0, abs=1e-9)


def test_a_right_bank_lifts_a_sight_line_to_the_right() -> None:
    # Right wing 30° down: a line 30° below the horizon to the right lies along the wing.
    rel = relative_pointing(math.radians(30), 0.0, 0.0, 90.0, -30.0)
    assert rel == pytest.approx((90.0, 0.0), abs=1e-9)


def test_quaternion_to_euler_yaw() -> None:
    half = math.radians(40) / 2
    roll, pitch, yaw = quaternion_to_euler(math.cos(half), 0.0, 0.0, math.sin(half))
    assert (roll, pitch) == pytest.approx((0.0, 0.0))
    assert math.degrees(yaw) == pytest.approx(40.0)


def test_flat_ground_at_45_degrees_is_as_far_as_it_is_below() -> None:
    hit = ground_intersection(65.86, 21.64, 600.0, 0.0, -45.0, flat, fallback_ground_msl_m=150.0)
    assert hit is not None
    assert hit.ground_range_m == pytest.approx(450.0, abs=0.1)  # curvature: 450²/2R = 1.6 cm
    distance, bearing = distance_bearing(65.86, 21.64, hit.lat_deg, hit.lon_deg)
    assert distance == pytest.approx(450.0, abs=0.1)
    assert bearing == pytest.approx(0.0, abs=1e-6)
    assert hit.slant_range_m == pytest.approx(450 * math.sqrt(2), abs=0.2)


def test_a_hill_in_the_way_is_hit_first() -> None:
    def hill(lat: float, _lon: float) -> float:
        return 400.0 if lat > 65.862 else 150.0  # a 400 m plateau from 220 m north

    hit = ground_intersection(65.86, 21.64, 600.0, 0.0, -45.0, hill)
    assert hit is not None
    # Flat, the ray lands 450 m out; it meets the plateau's face where it begins.
    edge_m, _ = distance_bearing(65.86, 21.64, 65.862, 21.64)
    assert hit.ground_range_m == pytest.approx(edge_m, abs=MIN_STEP_M)
    assert hit.elevation_msl_m in (150.0, 400.0)


@given(st.floats(-89, -1), st.floats(0, 359), st.floats(50, 5000))
def test_the_march_agrees_with_the_closed_form_on_flat_ground(
    elevation: float, azimuth: float, height: float
) -> None:
    marched = ground_intersection(
        58.4, 15.6, 100.0 + height, azimuth, elevation, flat, fallback_ground_msl_m=100.0
    )
    closed = flat_intersection(58.4, 15.6, 100.0 + height, azimuth, elevation, 100.0)
    assert (marched is None) == (closed is None)
    if marched is not None and closed is not None:
        assert marched.ground_range_m == pytest.approx(closed.ground_range_m, abs=0.5)


@pytest.mark.parametrize("elevation", [0.0, 10.0, -0.001])
def test_at_or_above_the_horizon_misses_the_earth(elevation: float) -> None:
    assert (
        ground_intersection(65.86, 21.64, 600.0, 0.0, elevation, flat, fallback_ground_msl_m=0.0)
        is None
    )


def test_no_ground_known_gives_nothing() -> None:
    assert ground_intersection(65.86, 21.64, 600.0, 0.0, -45.0, flat) is None


def test_footprint_width() -> None:
    assert footprint_width_m(1000.0, 90.0) == pytest.approx(2000.0)
