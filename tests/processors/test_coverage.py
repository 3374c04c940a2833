"""The survey's lawnmower (``processors._coverage``): its footprints cover the ordered area.

The union of the planned footprints is computed by ``tests/footprints.py`` (shapely when
installed, a raster otherwise) on geographiclib's plane, not the planner's.
"""

from __future__ import annotations

import math

import pytest
from footprints import covered_fraction

from processors._coverage import Survey, lawnmower, swath_m

AREAS = {
    "square": [(65.84, 21.02), (65.84, 21.06), (65.86, 21.06), (65.86, 21.02)],
    "triangle": [(65.84, 21.02), (65.84, 21.06), (65.86, 21.06)],
    "slanted": [(65.80, 21.00), (65.83, 21.10), (65.86, 21.08), (65.82, 20.98)],
    "concave": [(65.80, 21.0), (65.80, 21.1), (65.85, 21.1), (65.82, 21.05), (65.85, 21.0)],
}


@pytest.mark.parametrize("name", sorted(AREAS))
@pytest.mark.parametrize("overlap", [0.0, 0.2])
def test_the_footprints_cover_the_area(name: str, overlap: float) -> None:
    area = AREAS[name]
    survey = lawnmower(area, height_agl_m=400.0, hfov_deg=60.0, overlap=overlap, max_lines=100)
    assert isinstance(survey, Survey)
    assert survey.spacing_m <= survey.swath_m * (1 - overlap) + 1e-6
    assert covered_fraction(area, survey.points, survey.swath_m) >= 0.95


@pytest.mark.parametrize("name", sorted(AREAS))
def test_the_raster_and_shapely_agree(name: str) -> None:
    """Where shapely is not installed the raster decides: it must say what shapely says."""
    pytest.importorskip("shapely")
    area = AREAS[name]
    survey = lawnmower(area, height_agl_m=400.0, hfov_deg=60.0, overlap=0.0, max_lines=100)
    assert isinstance(survey, Survey)
    exact = covered_fraction(area, survey.points, survey.swath_m)
    raster = covered_fraction(area, survey.points, survey.swath_m, exact=False)
    assert raster == pytest.approx(exact, abs=0.01)


def test_a_sparse_pattern_is_found_short() -> None:
    """The measure can fail: lines twice the swath apart cover about half the area."""
    area = AREAS["square"]
    survey = lawnmower(area, height_agl_m=400.0, hfov_deg=60.0, overlap=0.0, max_lines=100)
    assert isinstance(survey, Survey)
    assert covered_fraction(area, survey.points, survey.swath_m / 2) < 0.6


def test_the_swath_is_the_footprint_at_the_height() -> None:
    assert swath_m(400.0, 60.0) == pytest.approx(800 * math.tan(math.radians(30)))
    low = lawnmower(AREAS["square"], height_agl_m=100.0, hfov_deg=60.0, overlap=0.2, max_lines=100)
    high = lawnmower(AREAS["square"], height_agl_m=400.0, hfov_deg=60.0, overlap=0.2, max_lines=100)
    assert isinstance(low, Survey)
    assert isinstance(high, Survey)
    assert low.lines > high.lines  # lower: narrower footprint, more lines


def test_too_many_lines_is_refused_with_its_numbers() -> None:
    got = lawnmower(AREAS["square"], height_agl_m=20.0, hfov_deg=30.0, overlap=0.5, max_lines=10)
    assert isinstance(got, str)
    assert got.startswith("the survey needs ")
    assert got.endswith("at most 10 are flown")
