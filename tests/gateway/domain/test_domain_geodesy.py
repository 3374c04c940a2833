"""Geodesy: MGRS and UTM zones against the mgrs package; distances; polar refusal."""

from __future__ import annotations

import random

import mgrs
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from gateway.domain.geodesy import (
    MgrsError,
    MgrsPrecision,
    destination,
    distance_bearing,
    from_mgrs,
    to_mgrs,
    utm_zone,
)
from gateway.testing import fuzz_examples

ORACLE = mgrs.MGRS()
DIGITS = {1: 5, 10: 4, 100: 3}
PRECISIONS: tuple[int, ...] = (1, 10, 100)


def random_points(seed: int) -> list[tuple[float, float]]:
    """10,000 points: 6,000 anywhere MGRS-on-UTM applies, 4,000 where the gateway works."""
    rng = random.Random(seed)
    points = [(rng.uniform(-80.0, 84.0), rng.uniform(-180.0, 180.0)) for _ in range(6_000)]
    points += [(rng.uniform(55.0, 69.5), rng.uniform(10.5, 24.5)) for _ in range(2_000)]  # Sweden
    points += [(rng.uniform(56.0, 64.0), rng.uniform(0.0, 12.0)) for _ in range(1_000)]  # 31V/32V
    points += [(rng.uniform(72.0, 84.0), rng.uniform(0.0, 42.0)) for _ in range(1_000)]  # Svalbard
    return points


def test_10000_points_agree_with_the_mgrs_package() -> None:
    """Encoding matches mgrs; decoding matches mgrs and lands within half a cell diagonal."""
    points = random_points(seed=26)
    assert len(points) == 10_000
    for index, (lat, lon) in enumerate(points):
        precision = PRECISIONS[index % 3]
        ours = to_mgrs(lat, lon, precision)  # type: ignore[arg-type]
        assert ours == ORACLE.toMGRS(lat, lon, MGRSPrecision=DIGITS[precision])
        ref = from_mgrs(ours)
        assert (ref.lat_deg, ref.lon_deg) == pytest.approx(ORACLE.toLatLon(ours), abs=1e-12)
        distance, _ = distance_bearing(lat, lon, ref.lat_deg, ref.lon_deg)
        # Truncation puts the point inside its cell, so it is at most half a diagonal from the
        # centre (plus a hair for the grid's scale factor near the zone edges).
        assert distance <= ref.uncertainty_m * 1.001 + 0.001


def test_utm_zone_rule_agrees_with_the_mgrs_package_on_10000_points() -> None:
    """The zone rule in code, Norway and Svalbard exceptions included, is the one mgrs uses."""
    for lat, lon in random_points(seed=27):
        reference = ORACLE.toMGRS(lat, lon, MGRSPrecision=0)  # e.g. '33VWE'
        assert utm_zone(lat, lon) == (int(reference[:-3]), reference[-3])


def near_a_zone_edge(lat: float, lon: float) -> bool:
    """Within 1e-7° (1 cm) of a zone or band edge, where mgrs rounds before choosing."""
    lon_edges = [-180.0 + 6 * i for i in range(61)] + [3.0, 9.0, 21.0, 33.0, 42.0]
    lat_edges = [-80.0 + 8 * i for i in range(20)] + [84.0]
    return (
        min(abs(lon - e) for e in lon_edges) < 1e-7 or min(abs(lat - e) for e in lat_edges) < 1e-7
    )


@settings(max_examples=fuzz_examples(2_000), deadline=None)
@given(
    st.floats(-80.0, 84.0),
    st.floats(-180.0, 180.0),
    st.sampled_from(PRECISIONS),
)
@example(-1e-9, 0.0, 1)  # found by the ra180 property test: the package's own dead end
def test_any_point_agrees_with_the_mgrs_package(lat: float, lon: float, precision: int) -> None:
    ours = to_mgrs(lat, lon, precision)  # type: ignore[arg-type]
    theirs = ORACLE.toMGRS(lat, lon, MGRSPrecision=DIGITS[precision])
    try:
        ORACLE.toLatLon(theirs)
    except mgrs.core.MGRSError:
        # A hair south of the equator the package can write a reference it cannot decode;
        # ours is then the equator's (test_a_point_a_hair_south_of_the_equator_...).
        assert -1e-7 < lat < 0.0
        assert ours == ORACLE.toMGRS(0.0, lon, MGRSPrecision=DIGITS[precision])
    else:
        assert ours == theirs
    if not near_a_zone_edge(lat, lon):
        # mgrs rounds coordinates by up to ~1e-8° before it picks a zone; the rule in code
        # does not, so the two may differ within a centimetre of an edge (checked below).
        square = ours[: len(ours) - 2 * DIGITS[precision]]  # e.g. '33VWE'
        assert utm_zone(lat, lon) == (int(square[:-3]), square[-3])


@pytest.mark.parametrize(("lat", "lon"), [(0.0, -1e-13), (60.0, 3.0 - 1e-15), (72.0 - 1e-12, 10.0)])
def test_within_a_hair_of_an_edge_the_mgrs_package_rounds_first(lat: float, lon: float) -> None:
    """The documented difference: mgrs snaps these onto the edge; the plain rule does not."""
    reference = ORACLE.toMGRS(lat, lon, MGRSPrecision=0)
    assert utm_zone(lat, lon) != (int(reference[:-3]), reference[-3])
    assert to_mgrs(lat, lon, 100).startswith(reference)


@pytest.mark.parametrize(
    ("lat", "lon", "prefix"),
    [
        (60.3913, 5.3221, "32VKN"),  # Bergen: zone 32 widened west over Norway
        (56.0, 3.0, "32VJH"),  # the widened zone's south-west corner
        (64.0, 3.0, "31WEL"),  # band W: no exception
        (58.4108, 15.6214, "33VWE"),  # Linköping
        (57.7089, 11.9746, "32VPK"),  # Göteborg, still zone 32
        (58.0, 12.0, "33VUE"),  # ... and 12° E is zone 33
        (59.3293, 18.0686, "34VCL"),  # Stockholm
        (67.8558, 20.2253, "34WDA"),  # Kiruna
        (65.83, 24.15, "35WLP"),  # Haparanda
        (79.0, 9.5, "33XUH"),  # Svalbard: 32X does not exist
        (78.22, 15.65, "33XWG"),  # Longyearbyen
        (84.0, 15.0, "33XWP"),  # the northern edge is still UTM
        (-80.0, 15.0, "33CWM"),  # and so is the southern one
    ],
)
def test_zone_exceptions_and_nordic_places(lat: float, lon: float, prefix: str) -> None:
    assert to_mgrs(lat, lon).startswith(prefix)


def test_truncates_and_formats_with_spaces() -> None:
    """UTM E 536308.5 truncates to 36308 (specs/mgrs_sidc.md); spaces for display only."""
    assert to_mgrs(58.4108, 15.6214, 1, spaced=True) == "33V WE 36308 74614"
    assert to_mgrs(58.4108, 15.6214, 10) == "33VWE36307461"
    assert to_mgrs(58.4108, 15.6214, 100) == "33VWE363746"
    ref = from_mgrs("33v we 363 746")
    assert (ref.precision_m, ref.uncertainty_m) == (100, pytest.approx(70.7107, abs=1e-4))


def test_antimeridian_is_zone_1_as_in_mgrs() -> None:
    assert to_mgrs(10.0, 180.0) == to_mgrs(10.0, -180.0) == ORACLE.toMGRS(10.0, 180.0)
    assert utm_zone(10.0, 180.0) == (1, "P")


@pytest.mark.parametrize(("lat", "lon"), [(84.01, 10.0), (85.0, 10.0), (-80.01, 45.0), (-90, 0)])
def test_polar_points_are_refused_clearly(lat: float, lon: float) -> None:
    with pytest.raises(MgrsError, match=r"polar \(UPS\)"):
        to_mgrs(lat, lon)
    with pytest.raises(MgrsError, match="polar"):
        utm_zone(lat, lon)


@pytest.mark.parametrize("text", ["ZAB 96454 52981", "bkv0794807948"])
def test_polar_references_are_refused_clearly(text: str) -> None:
    with pytest.raises(MgrsError, match=r"polar \(UPS\)"):
        from_mgrs(text)


@pytest.mark.parametrize(
    "text", ["", "33VWE36374", "hello", "33VWE1234567890123", "33VWE", "60XWA000000", "32XNA000000"]
)
def test_malformed_references_are_refused(text: str) -> None:
    with pytest.raises(MgrsError):
        from_mgrs(text)


@pytest.mark.parametrize(
    ("lat", "lon", "precision"),
    [(91.0, 0.0, 1), (0.0, 181.0, 1), (float("nan"), 0.0, 1), (0.0, 0.0, 1000)],
)
def test_bad_input_is_refused(lat: float, lon: float, precision: int) -> None:
    with pytest.raises(MgrsError):
        to_mgrs(lat, lon, precision)  # type: ignore[arg-type]


def test_distance_and_bearing_round_trip() -> None:
    lat, lon = destination(65.8252, 21.6886, 45.0, 10_000.0)
    distance, bearing = distance_bearing(65.8252, 21.6886, lat, lon)
    assert distance == pytest.approx(10_000.0, abs=1e-6)
    assert bearing == pytest.approx(45.0, abs=1e-9)


def test_distance_on_a_meridian_is_the_ellipsoid_arc() -> None:
    """One degree of latitude at 60° N is 111,412.2 m on WGS 84 (not 111,195 m of a sphere)."""
    distance, bearing = distance_bearing(59.5, 15.0, 60.5, 15.0)
    assert distance == pytest.approx(111_412.2, abs=1.0)
    assert bearing == pytest.approx(0.0, abs=1e-9)


def test_a_reference_outside_its_latitude_band_is_refused_not_warned_through() -> None:
    # Zone 4, band N, square AA: the mgrs package decodes it with a RuntimeWarning ("Latitude
    # Warning") to a point outside band N; an order or a CDM naming it is malformed.
    with pytest.raises(MgrsError, match="'4NAA 6602 0000': the grid square is not in its band"):
        from_mgrs("4NAA 6602 0000")


@pytest.mark.parametrize("lat", [-1e-9, -5e-8, -0.0, 0.0, -1e-7, -1e-5])
@pytest.mark.parametrize("precision", [1, 10, 100])
def test_a_point_a_hair_south_of_the_equator_gets_a_reference_that_decodes(
    lat: float, precision: MgrsPrecision
) -> None:
    """The package wrote ``31MAA 66021 00000`` for 1e-9° S, which nothing decodes."""
    ref = from_mgrs(to_mgrs(lat, 0.0, precision))
    assert abs(ref.lat_deg - lat) * 111_320 <= ref.uncertainty_m + 0.02
