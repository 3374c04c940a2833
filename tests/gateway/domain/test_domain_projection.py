"""Transverse Mercator for DEM grids, against pyproj's figures and the mgrs package's UTM."""

from __future__ import annotations

import math
import random

import mgrs
import pytest

from gateway.domain.projection import (
    GEOGRAPHIC,
    ProjectionError,
    TransverseMercator,
    crs_from_epsg,
)

# (EPSG, lat, lon, easting, northing) computed with pyproj 3.7.2 (PROJ), which this project
# does not depend on: SWEREF 99 TM and a local zone, ETRS-TM35FIN, ETRS89 and WGS 84 UTM.
PYPROJ = [
    (3006, 58.4108, 15.6214, 536308.536, 6474614.999),  # Linköping
    (3006, 67.8558, 20.2253, 719583.123, 7536069.970),  # Kiruna
    (3006, 55.605, 13.0038, 374243.759, 6163926.553),  # Malmö
    (3006, 65.83, 24.15, 916865.052, 7331416.181),  # Haparanda, 9° off the meridian
    (3011, 59.3293, 18.0686, 153905.093, 6579354.448),  # Stockholm, SWEREF 99 18 00
    (3067, 60.1699, 24.9384, 385611.317, 6672118.380),  # Helsinki
    (25833, 78.2232, 15.6267, 514278.715, 8683355.469),  # Longyearbyen
    (32633, 58.4108, 15.6214, 536308.536, 6474614.999),
    (32734, -33.9249, 18.4241, 261881.599, 6243182.355),  # Cape Town, southern hemisphere
]


@pytest.mark.parametrize(("epsg", "lat", "lon", "easting", "northing"), PYPROJ)
def test_forward_matches_pyproj_to_a_millimetre(
    epsg: int, lat: float, lon: float, easting: float, northing: float
) -> None:
    x, y = crs_from_epsg(epsg).forward(lat, lon)
    assert (x, y) == pytest.approx((easting, northing), abs=1e-3)


def test_sweref99_tm_matches_utm_33_from_the_mgrs_package() -> None:
    """SWEREF 99 TM is UTM zone 33 on GRS 80; mgrs gives the 1 m cell centre (±0.5 m)."""
    oracle, sweref = mgrs.MGRS(), crs_from_epsg(3006)
    rng = random.Random(3006)
    for _ in range(2_000):
        lat, lon = rng.uniform(55.0, 69.0), rng.uniform(12.0, 17.999)
        zone, _, easting, northing = oracle.MGRSToUTM(oracle.toMGRS(lat, lon, MGRSPrecision=5))
        assert zone == 33
        x, y = sweref.forward(lat, lon)
        assert abs(x - easting) <= 0.5 + 1e-3  # GeoTrans is good to about 1 mm
        assert abs(y - northing) <= 0.5 + 1e-3


def test_geographic_is_lon_lat() -> None:
    assert GEOGRAPHIC.forward(58.5, 15.25) == (15.25, 58.5)
    assert crs_from_epsg(4619).forward(58.5, 15.25) == (15.25, 58.5)


def test_far_from_the_meridian_gives_nan() -> None:
    """No grid in SWEREF 99 TM lies on the other side of the globe; the series fails there."""
    assert all(math.isnan(v) for v in crs_from_epsg(3006).forward(0.0, 105.0))
    # Longitude wraps: 179 W is 166 degrees from 15 E, not 194.
    assert all(math.isnan(v) for v in crs_from_epsg(3006).forward(60.0, -179.0))
    x, _ = crs_from_epsg(32601).forward(10.0, 179.0)  # zone 1 spans the antimeridian side
    assert math.isfinite(x)


@pytest.mark.parametrize("epsg", [3857, 2154, 32767, 0])
def test_unknown_epsg_is_named(epsg: int) -> None:
    with pytest.raises(ProjectionError, match=f"EPSG:{epsg} is not supported"):
        crs_from_epsg(epsg)


def test_repr_names_the_code() -> None:
    crs = crs_from_epsg(3006)
    assert isinstance(crs, TransverseMercator)
    assert repr(crs) == "TransverseMercator(epsg=3006, lon0_deg=15.0)"
