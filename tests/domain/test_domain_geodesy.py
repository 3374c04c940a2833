"""Geodesy: MGRS against the mgrs package and geographiclib; distances; polar refusal."""

from __future__ import annotations

import random

import mgrs
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.domain.geodesy import MgrsError, destination, distance_bearing, from_mgrs, to_mgrs
from gateway.testing import fuzz_examples

ORACLE = mgrs.MGRS()
DIGITS = {1: 5, 10: 4, 100: 3}


def random_points(n: int, seed: int) -> list[tuple[float, float]]:
    rng = random.Random(seed)
    points = [(rng.uniform(-80.0, 84.0), rng.uniform(-180.0, 179.999)) for _ in range(n)]
    # Weight the regions the gateway works in: Sweden, Norway's zone 32V and Svalbard.
    points += [(rng.uniform(55.0, 69.5), rng.uniform(10.5, 24.5)) for _ in range(n // 4)]
    points += [(rng.uniform(56.0, 64.0), rng.uniform(0.0, 12.0)) for _ in range(n // 8)]
    points += [(rng.uniform(72.0, 84.0), rng.uniform(0.0, 42.0)) for _ in range(n // 8)]
    return points


def test_10000_points_agree_with_the_mgrs_package_and_decode_inside_the_cell() -> None:
    points = random_points(6_700, seed=26)
    assert len(points) >= 10_000
    for index, (lat, lon) in enumerate(points):
        precision = (1, 10, 100)[index % 3]
        ours = to_mgrs(lat, lon, precision)  # type: ignore[arg-type]
        assert ours == ORACLE.toMGRS(lat, lon, MGRSPrecision=DIGITS[precision])
        ref = from_mgrs(ours)
        distance, _ = distance_bearing(lat, lon, ref.lat_deg, ref.lon_deg)
        # Truncation puts the point inside the cell; the centre is at most half a diagonal
        # away (plus a hair for the grid's scale factor and convergence).
        assert distance <= ref.uncertainty_m * 1.01 + 0.01


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(st.floats(-80.0, 84.0), st.floats(-180.0, 179.999), st.sampled_from([1, 10, 100]))
def test_any_point_agrees_with_the_mgrs_package(lat: float, lon: float, precision: int) -> None:
    assert to_mgrs(lat, lon, precision) == ORACLE.toMGRS(  # type: ignore[arg-type]
        lat, lon, MGRSPrecision=DIGITS[precision]
    )


@pytest.mark.parametrize(
    ("lat", "lon", "prefix"),
    [
        (60.3913, 5.3221, "32VKN"),  # Bergen: zone 32 widened west over Norway
        (58.4108, 15.6214, "33VWE"),  # Linköping
        (57.7089, 11.9746, "32VPK"),  # Göteborg, still zone 32
        (65.83, 24.15, "35WLP"),  # Haparanda
        (79.0, 9.5, "33XUH"),  # Svalbard: 32X does not exist
        (78.22, 15.65, "33XWG"),  # Longyearbyen
        (84.0, 15.0, "33XWP"),  # the northern edge is still UTM
    ],
)
def test_zone_exceptions_and_swedish_places(lat: float, lon: float, prefix: str) -> None:
    assert to_mgrs(lat, lon).startswith(prefix)


def test_truncates_and_formats_with_spaces() -> None:
    assert to_mgrs(58.4108, 15.6214, 1, spaced=True) == "33V WE 36308 74614"
    assert to_mgrs(58.4108, 15.6214, 100) == "33VWE363746"
    assert from_mgrs("33v we 363 746").precision_m == 100


@pytest.mark.parametrize(("lat", "lon"), [(84.01, 10.0), (85.0, 10.0), (-80.01, 45.0), (-90, 0)])
def test_polar_points_are_refused_clearly(lat: float, lon: float) -> None:
    with pytest.raises(MgrsError, match="polar"):
        to_mgrs(lat, lon)


@pytest.mark.parametrize("text", ["", "33VWE36374", "hello", "33VWE1234567890123"])
def test_malformed_references_are_refused(text: str) -> None:
    with pytest.raises(MgrsError):
        from_mgrs(text)


def test_distance_and_bearing_round_trip() -> None:
    lat, lon = destination(65.8252, 21.6886, 45.0, 10_000.0)
    distance, bearing = distance_bearing(65.8252, 21.6886, lat, lon)
    assert distance == pytest.approx(10_000.0, abs=1e-6)
    assert bearing == pytest.approx(45.0, abs=1e-9)
