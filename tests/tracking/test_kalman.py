"""The plain-float constant-velocity filter against the textbook matrix formulas (numpy)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tracking.kalman import POSITION, VELOCITY, Estimate


def _random_estimate(seed: int) -> Estimate:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(4, 4))
    p = a @ a.T + 4.0 * np.eye(4)  # symmetric positive definite
    return Estimate(rng.normal(scale=50.0, size=4).tolist(), p.flatten().tolist())


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(min_value=0, max_value=10_000),
    dt=st.floats(min_value=0.0, max_value=30.0),
    q=st.floats(min_value=0.0, max_value=20.0),
)
def test_predict_is_f_p_ft_plus_q(seed: int, dt: float, q: float) -> None:
    est = _random_estimate(seed)
    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt
    block = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    qm = np.zeros((4, 4))
    qm[np.ix_([0, 2], [0, 2])] = block
    qm[np.ix_([1, 3], [1, 3])] = block
    p = np.array(est.p).reshape(4, 4)
    out = est.predicted(dt, q)
    assert np.allclose(np.array(out.x), f @ np.array(est.x))
    assert np.allclose(np.array(out.p).reshape(4, 4), f @ p @ f.T + qm)


@pytest.mark.parametrize("pair", [POSITION, VELOCITY])
@settings(max_examples=30, deadline=None)
@given(seed=st.integers(min_value=0, max_value=10_000))
def test_update_is_the_kalman_update(pair: tuple[int, int], seed: int) -> None:
    est = _random_estimate(seed)
    rng = np.random.default_rng(seed + 1)
    z = rng.normal(scale=60.0, size=2)
    r = np.array([[30.0, 4.0], [4.0, 20.0]])
    h = np.zeros((2, 4))
    h[0, pair[0]] = h[1, pair[1]] = 1.0
    x, p = np.array(est.x), np.array(est.p).reshape(4, 4)
    s = h @ p @ h.T + r
    k = p @ h.T @ np.linalg.inv(s)
    innovation = est.innovation(z[0], z[1], r[0, 0], r[0, 1], r[1, 1], pair)
    y = z - h @ x
    assert innovation.d2 == pytest.approx(float(y @ np.linalg.inv(s) @ y))
    assert innovation.cost == pytest.approx(innovation.d2 + float(np.log(np.linalg.det(s))))
    est.update(innovation, pair)
    assert np.allclose(np.array(est.x), x + k @ y)
    assert np.allclose(np.array(est.p).reshape(4, 4), p - k @ s @ k.T)


def test_the_speed_prior_moves_the_speed_along_the_course_and_keeps_the_covariance() -> None:
    """A class's speed limit says how fast, not where to: the pull changes the velocity along
    its course by a measurement's gain and leaves every variance as it was."""
    from tracking.kalman import Estimate

    estimate = Estimate.at_rest(10.0, 20.0)
    estimate.x[2], estimate.x[3] = 30.0, 0.0  # 30 m/s due east, over a 20 m/s limit
    before = list(estimate.p)
    r = 4.0**2
    estimate.update_speed(1.0, 0.0, 20.0, r)
    gain = 20.0**2 / (20.0**2 + r)
    assert estimate.x[2] == pytest.approx(30.0 + gain * (20.0 - 30.0))
    assert estimate.x[3] == 0.0  # across the course: untouched
    assert estimate.p == before
