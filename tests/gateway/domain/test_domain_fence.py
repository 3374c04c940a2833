"""The geofence on the ellipsoid: geodesic edges, legs flown as geodesic and rhumb line.

The reference the property test holds the plane tests to is independent of them: the fence's
edges and the leg sampled densely with geographiclib, point-in-polygon in latitude and
longitude on the sampled ring, distances in the local north-east metres of each sample.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from geographiclib.geodesic import Geodesic  # type: ignore[import-untyped]
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st

from gateway.domain.fence import Fence, FenceError
from gateway.domain.mission import polygon_problem, route_exit
from gateway.domain.paths import rhumb_at, rhumb_bow_m, rhumb_points

G = Geodesic.WGS84
E2 = G.f * (2 - G.f)
#: The example fence of docs/orders.md: its edges are 188 km (65° N) and 174 km (67° N) long.
EXAMPLE = [(65.0, 20.0), (65.0, 24.0), (67.0, 24.0), (67.0, 20.0)]

LatLon = tuple[float, float]


def geodesic_samples(a: LatLon, b: LatLon, spacing_m: float) -> list[LatLon]:
    line = G.InverseLine(*a, *b)
    n = max(1, math.ceil(line.s13 / spacing_m))
    return [(p["lat2"], p["lon2"]) for p in (line.Position(line.s13 * i / n) for i in range(n + 1))]


def ring(fence: list[LatLon], spacing_m: float = 1000.0) -> np.ndarray:
    """The fence's edges as dense geodesic samples (a chord of 1 km is within 0.1 m of the
    geodesic, in latitude and longitude, up to 75° of latitude)."""
    points: list[LatLon] = []
    for a, b in zip(fence, fence[1:] + fence[:1], strict=True):
        points.extend(geodesic_samples(a, b, spacing_m)[:-1])
    return np.array([*points, points[0]])


def reference_outside_m(fence_ring: np.ndarray, points: list[LatLon]) -> np.ndarray:
    """How far each point is outside the sampled ring (m); negative inside: minus the
    distance to the ring."""
    pts = np.array(points)
    plat, plon = pts[:, :1], pts[:, 1:]
    a_lat, b_lat = fence_ring[None, :-1, 0], fence_ring[None, 1:, 0]
    a_lon, b_lon = fence_ring[None, :-1, 1], fence_ring[None, 1:, 1]
    spans = (a_lat > plat) != (b_lat > plat)
    with np.errstate(divide="ignore", invalid="ignore"):
        cross = a_lon + (plat - a_lat) * (b_lon - a_lon) / (b_lat - a_lat)
    is_in = np.count_nonzero(spans & (plon < cross), axis=1) % 2 == 1
    s = np.sin(np.radians(plat))
    north = math.radians(1) * G.a * (1 - E2) / (1 - E2 * s * s) ** 1.5
    east = math.radians(1) * G.a / np.sqrt(1 - E2 * s * s) * np.cos(np.radians(plat))
    ax, ay = (a_lon - plon) * east, (a_lat - plat) * north
    bx, by = (b_lon - plon) * east, (b_lat - plat) * north
    dx, dy = bx - ax, by - ay
    t = np.clip(-(ax * dx + ay * dy) / np.maximum(dx * dx + dy * dy, 1e-12), 0.0, 1.0)
    distance = np.min(np.hypot(ax + t * dx, ay + t * dy), axis=1)
    return np.where(is_in, -distance, distance)


def planar_inside(fence: list[LatLon], point: LatLon) -> bool:
    """The check as it was: ray casting in latitude and longitude (edges along parallels)."""
    is_in = False
    for (y1, x1), (y2, x2) in zip(fence, fence[1:] + fence[:1], strict=True):
        if (y1 > point[0]) != (y2 > point[0]) and point[1] < x1 + (point[0] - y1) * (x2 - x1) / (
            y2 - y1
        ):
            is_in = not is_in
        if y1 == y2 == point[0] and min(x1, x2) <= point[1] <= max(x1, x2):
            return True
    return is_in


class TestTheRedTeamsLeg:
    """A 170 km leg along the example fence's 65° N edge, 89 m north of the parallel."""

    LEG = ((65.0008, 20.2), (65.0008, 23.8))

    def test_planar_said_inside_the_geodesic_is_194_m_outside(self) -> None:
        a, b = self.LEG
        assert 169_000 < G.Inverse(*a, *b)["s12"] < 171_000
        samples = geodesic_samples(a, b, 200.0)
        assert all(planar_inside(EXAMPLE, p) for p in (a, b))
        # The edge is the geodesic (65 N, 20 E)-(65 N, 24 E): 1.5 km north of 65 N at 22 E.
        reference = reference_outside_m(ring(EXAMPLE, 500.0), samples)
        assert reference.min() > 180.0  # the whole leg is outside, its ends too
        got = route_exit(EXAMPLE, [a, b])
        assert got is not None
        assert got.outside_m == pytest.approx(float(reference.max()), abs=1.0)
        assert 190.0 < got.outside_m < 200.0

    def test_the_same_leg_at_the_north_edge_is_inside(self) -> None:
        """The 67 N edge bows 1.6 km north, further than the leg's own geodesic."""
        assert route_exit(EXAMPLE, [(66.9992, 20.2), (66.9992, 23.8)]) is None

    def test_the_rhumb_line_arduPilot_flies_is_checked_too(self) -> None:
        """Both ends 300 m inside, the geodesic inside; the parallel between them (an
        east-west leg as ArduPilot flies it) is 1 km south of the bowed edge."""
        a, b = (65.004, 20.1), (65.004, 23.9)
        reference = reference_outside_m(ring(EXAMPLE, 500.0), geodesic_samples(a, b, 200.0))
        assert reference.max() < 0.0
        got = route_exit(EXAMPLE, [a, b])
        assert got is not None
        assert got.path == "rhumb line"
        assert got.leg == (a, b)
        rhumb = [rhumb_at(a, b, i / 400) for i in range(401)]
        expected = float(reference_outside_m(ring(EXAMPLE, 500.0), rhumb).max())
        assert got.outside_m == pytest.approx(expected, abs=1.0)
        assert got.point[1] == pytest.approx(22.0, abs=0.05)


def test_a_geodesic_leg_leaves_past_a_notch_the_planar_check_passed() -> None:
    """A notch in the north edge points south to 65.6 N; the leg passes 220 m south of its
    tip in latitude and longitude, but its geodesic bows north round the tip."""
    fence = [(65.0, 20.0), (65.0, 24.0), (67.0, 24.0), (65.6, 22.0), (67.0, 20.0)]
    a, b = (65.598, 20.9), (65.598, 23.1)
    line = [(a[0], a[1] + (b[1] - a[1]) * i / 200) for i in range(201)]
    assert all(planar_inside(fence, p) for p in line)
    # The farthest point is where the two edges from the tip are equally near: a kink,
    # so the reference is sampled every metre round the tip.
    line = G.InverseLine(*a, *b)
    middle = [line.Position(line.s13 / 2 + d) for d in np.arange(-500.0, 500.0, 1.0)]
    samples = geodesic_samples(a, b, 200.0) + [(p["lat2"], p["lon2"]) for p in middle]
    reference = reference_outside_m(ring(fence, 500.0), samples)
    got = route_exit(fence, [a, b])
    assert got is not None
    assert got.path == "geodesic"
    assert got.outside_m == pytest.approx(float(reference.max()), abs=1.0)
    assert got.outside_m > 100.0


def test_the_plane_keeps_geodesics_straight_to_a_centimetre_within_300_km() -> None:
    fence = Fence([(64.0, 20.0), (64.0, 26.0), (68.0, 26.0), (68.0, 20.0)])
    a, b = fence.corners[0], fence.corners[2]
    pa, pb = fence.project(a), fence.project(b)
    assert pa is not None
    assert pb is not None
    dx, dy = pb[0] - pa[0], pb[1] - pa[1]
    worst = 0.0
    for p in geodesic_samples(a, b, 2000.0):
        got = fence.project(p)
        assert got is not None
        worst = max(worst, abs((got[0] - pa[0]) * dy - (got[1] - pa[1]) * dx) / math.hypot(dx, dy))
    assert worst < 0.01


def test_a_fence_too_big_for_the_plane_is_named() -> None:
    huge = [(0.0, 0.0), (0.0, 30.0), (20.0, 30.0), (20.0, 0.0)]
    assert polygon_problem(huge) == (
        "reaches more than 1000 km from its centre at corner 1; split it into smaller ones"
    )
    with pytest.raises(FenceError, match="1000 km"):
        Fence(huge)


def test_a_leg_across_the_antimeridian_inside_a_fence_across_it() -> None:
    fence = [(65.0, 179.0), (65.0, -179.0), (66.0, -179.0), (66.0, 179.0)]
    assert route_exit(fence, [(65.5, 179.2), (65.5, -179.2)]) is None
    got = route_exit(fence, [(65.5, 179.2), (64.9, -179.5)])
    assert got is not None
    assert got.leg is None


def test_rhumb_points_of_an_east_west_leg_keep_its_latitude() -> None:
    points = rhumb_points((65.0, 179.0), (65.0, -179.0), 4)
    assert [round(p[0], 9) for p in points] == [65.0] * 5
    assert [round(p[1], 6) for p in points] == [179.0, 179.5, -180.0, -179.5, -179.0]


@pytest.mark.parametrize(
    ("a", "b"), [((65.0, 20.0), (65.0, 24.0)), ((60.0, 10.0), (61.5, 13.0)), ((-40.0, 0), (-41, 2))]
)
def test_the_rhumb_bow_is_an_upper_estimate_of_the_two_paths_parting(a: LatLon, b: LatLon) -> None:
    length = G.Inverse(*a, *b)["s12"]
    fence = Fence([a, b, ((a[0] + b[0]) / 2 + 1.0, (a[1] + b[1]) / 2)])
    pa, pb = fence.project(a), fence.project(b)
    assert pa is not None
    assert pb is not None
    dx, dy = pb[0] - pa[0], pb[1] - pa[1]
    parted = 0.0
    for i in range(1, 100):
        got = fence.project(rhumb_at(a, b, i / 100))
        assert got is not None
        off = abs((got[0] - pa[0]) * dy - (got[1] - pa[1]) * dx) / math.hypot(dx, dy)
        parted = max(parted, off * got[2])
    bow = rhumb_bow_m(a, b, length)
    assert parted <= bow <= 1.05 * parted


@st.composite
def fence_and_leg(draw: st.DrawFn) -> tuple[list[LatLon], LatLon, LatLon]:
    lat0 = draw(st.floats(-70.0, 70.0))
    lon0 = draw(st.floats(-160.0, 160.0))
    n = draw(st.integers(3, 7))
    # Corners round the centre with no gap over 163°: a star-shaped fence about it.
    weights = draw(st.lists(st.floats(0.6, 1.0), min_size=n, max_size=n))
    start = draw(st.floats(0.0, 360.0))
    bearings = [start + 360.0 * sum(weights[:i]) / sum(weights) for i in range(n)]
    radii = draw(st.lists(st.floats(5_000.0, 100_000.0), min_size=n, max_size=n))
    mode = draw(st.sampled_from(["anywhere", "arms", "edge", "notch"]))
    first = draw(st.integers(0, n - 1))
    if mode == "notch":  # the corner between the two ends pulled in: a leg across a notch
        radii[(first + 1) % n] *= draw(st.floats(0.05, 0.6))
    fence = []
    for bearing, radius in zip(bearings, radii, strict=True):
        got = G.Direct(lat0, lon0, bearing, radius)
        fence.append((got["lat2"], got["lon2"]))
    ends = []
    for k in range(2):
        if mode == "anywhere":
            bearing, distance = draw(st.floats(0.0, 360.0)), draw(st.floats(0.0, 75_000.0))
        else:
            # Towards a corner, just inside: legs between the star's arms may cross its
            # notches; legs from one end of an edge to the other run along it (the rhumb
            # line may leave).
            corner = {
                "arms": draw(st.integers(0, n - 1)),
                "edge": (first + k) % n,
                "notch": (first + 2 * k) % n,
            }[mode]
            low = 0.5 if mode == "arms" else 0.97
            bearing, distance = bearings[corner], radii[corner] * draw(st.floats(low, 0.9999))
        got = G.Direct(lat0, lon0, bearing, distance)
        ends.append((got["lat2"], got["lon2"]))
    return fence, ends[0], ends[1]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fence_and_leg())
def test_the_verdict_and_distance_agree_with_dense_geodesic_sampling(
    case: tuple[list[LatLon], LatLon, LatLon],
) -> None:
    fence, a, b = case
    assume(polygon_problem(fence) is None)
    samples = geodesic_samples(a, b, 100.0)
    length = G.Inverse(*a, *b)["s12"]
    if rhumb_bow_m(a, b, length) > 1.0:
        n = max(1, math.ceil(length / 100.0))
        samples += [rhumb_at(a, b, i / n) for i in range(n + 1)]
    reference = reference_outside_m(ring(fence), samples)
    worst = float(reference.max())
    got = route_exit(fence, [a, b])
    event("outside" if worst > 60.0 else "inside" if worst < -1.0 else "within 60 m of an edge")
    if got is not None:
        event(f"named {'a point' if got.leg is None else got.path}")
    if worst > 60.0:
        assert got is not None
        if got.leg is None:  # a route point outside: the first is named, with its distance
            assert got.point in (a, b)
            (at_point,) = reference_outside_m(ring(fence), [got.point])
            assert got.outside_m == pytest.approx(float(at_point), rel=0.01, abs=1.0)
        else:
            # The reference samples every 100 m (its maximum may be up to 50 m short), and
            # its flat north-east metres are off by 0.1 % at 10 km from the ring.
            assert 0.995 * worst - 1.0 <= got.outside_m <= 1.01 * worst + 51.0
    elif worst < -1.0:
        assert got is None


def test_a_chord_between_two_edge_points_across_a_notch_leaves() -> None:
    """Both ends on the fence's edge (inside), the chord between them only outside."""
    u_fence = [
        (65.0, 20.0),
        (65.0, 22.0),
        (66.0, 22.0),
        (66.0, 21.3),
        (65.3, 21.3),
        (65.3, 20.7),
        (66.0, 20.7),
        (66.0, 20.0),
    ]
    got = route_exit(u_fence, [(65.6, 20.7), (65.6, 21.3)])
    assert got is not None
    assert got.leg is not None
