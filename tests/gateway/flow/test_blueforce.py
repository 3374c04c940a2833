"""The blue-force registry: newest report per unit, expiry, geodesic nearest, bounded."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
from geographiclib.geodesic import Geodesic
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.events import BlueForce, Position
from gateway.flow.blueforce import BlueForceRegistry

NOW = datetime(2026, 11, 23, 12, tzinfo=UTC)


def report(uid: str, lat: float, lon: float, age_s: float = 0.0) -> BlueForce:
    time = NOW - timedelta(seconds=age_s)
    return BlueForce(
        event_id=f"{uid}-{age_s}", uid=uid, callsign=uid, time=time,
        position=Position(lat_deg=lat, lon_deg=lon), source="test",
    )  # fmt: skip


def test_nearest_current_unit_by_wgs84_distance() -> None:
    registry = BlueForceRegistry(lambda: NOW, max_age_s=300)
    registry.update(report("P1", 65.80, 21.70))
    registry.update(report("P2", 65.83, 21.69))
    registry.update(report("OLD", 65.8252, 21.6886, age_s=600))  # stale: never returned
    nearest = registry.nearest(65.8252, 21.6886)
    assert nearest is not None
    assert nearest.uid == "P2"
    expected = Geodesic.WGS84.Inverse(65.8252, 21.6886, 65.83, 21.69)["s12"]
    assert nearest.distance_m == pytest.approx(expected, abs=0.01)
    assert len(registry) == 2  # the stale report was dropped on the way


def test_an_older_report_never_moves_a_unit_back() -> None:
    registry = BlueForceRegistry(lambda: NOW)
    assert registry.update(report("P1", 65.80, 21.70, age_s=10))
    assert not registry.update(report("P1", 60.0, 20.0, age_s=20))
    assert registry.current()[0].position.lat_deg == 65.80


def test_the_registry_is_bounded() -> None:
    registry = BlueForceRegistry(lambda: NOW, max_units=3)
    for n in range(10):
        registry.update(report(f"U{n}", 65.0, 21.0 + n / 100))
    assert len(registry) == 3
    assert {r.uid for r in registry.current()} == {"U7", "U8", "U9"}


def test_no_unit_no_nearest() -> None:
    assert BlueForceRegistry(lambda: NOW).nearest(65.0, 21.0) is None


lats = st.floats(-89.9, 89.9, allow_nan=False)
lons = st.floats(-180.0, 180.0, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    st.tuples(lats, lons),
    st.lists(st.tuples(lats, lons), min_size=1, max_size=30),
    st.floats(0.0, 0.2),
)
def test_the_cheap_ranking_never_misses_the_geodesic_nearest(
    point: tuple[float, float], units: list[tuple[float, float]], spread: float
) -> None:
    """The sphere pre-filter keeps every unit that could be nearest on the ellipsoid."""
    registry = BlueForceRegistry(lambda: NOW, max_age_s=300, max_units=100)
    lat, lon = point
    for i, (ulat, ulon) in enumerate(units):
        # Half the units clustered near the point, so near-ties are common.
        if i % 2:
            ulat = max(-89.9, min(89.9, lat + (ulat / 90.0) * spread))
            ulon = ((lon + (ulon / 180.0) * spread) + 180.0) % 360.0 - 180.0
        registry.update(report(f"U{i}", ulat, ulon))
    nearest = registry.nearest(lat, lon)
    assert nearest is not None
    expected = min(
        Geodesic.WGS84.Inverse(lat, lon, u.position.lat_deg, u.position.lon_deg)["s12"]
        for u in registry.current()
    )
    assert nearest.distance_m == pytest.approx(expected, abs=1e-6)
