"""A constant-velocity Kalman filter in a track's local east/north plane, in plain floats.

The state is ``x = (east, north, v_east, v_north)`` in metres and m/s about an anchor point
(``tracking.track`` re-anchors after each update, so positions stay small); the covariance
``P`` is the full symmetric 4×4 matrix, row-major in a list of 16. Pure Python on purpose: for
a 4×4 filter the interpreter is faster than numpy's per-call overhead, and it needs no extra.

Process noise is the continuous white-noise acceleration model with spectral density ``q``
(m²/s³) per axis: over Δt it adds q·[[Δt³/3, Δt²/2], [Δt²/2, Δt]] to each axis's
(position, velocity) block. Measurements observe a pair of state components (positions, or
velocities for the speed prior) with a 2×2 covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Estimate", "Innovation"]

#: Indices of the observed pairs: positions (east, north), velocities (east, north).
POSITION = (0, 1)
VELOCITY = (2, 3)


@dataclass(frozen=True, slots=True)
class Innovation:
    """A measurement against a predicted estimate: residual, its covariance S and d²."""

    ye: float
    yn: float
    s00: float
    s01: float
    s11: float

    @property
    def det(self) -> float:
        """det S (m⁴ for positions)."""
        return self.s00 * self.s11 - self.s01 * self.s01

    @property
    def d2(self) -> float:
        """The squared Mahalanobis distance yᵀS⁻¹y (∞ when S is singular)."""
        det = self.det
        if not det > 0.0:
            return math.inf
        ye, yn = self.ye, self.yn
        return (self.s11 * ye * ye - 2.0 * self.s01 * ye * yn + self.s00 * yn * yn) / det

    @property
    def cost(self) -> float:
        """d² + ln det S: the negative log-likelihood (up to a constant) used to assign."""
        det = self.det
        return self.d2 + math.log(det) if det > 0.0 else math.inf


@dataclass(slots=True)
class Estimate:
    """State and covariance of one constant-velocity target."""

    x: list[float]
    p: list[float]

    @classmethod
    def at_rest(cls, sigma_m: float, sigma_v: float) -> Estimate:
        """At the anchor with position σ ``sigma_m`` and velocity σ ``sigma_v`` per axis."""
        pos, vel = sigma_m * sigma_m, sigma_v * sigma_v
        p = [0.0] * 16
        p[0] = p[5] = pos
        p[10] = p[15] = vel
        return cls([0.0, 0.0, 0.0, 0.0], p)

    def copy(self) -> Estimate:
        """An independent copy."""
        return Estimate(list(self.x), list(self.p))

    def predicted(self, dt: float, q: float) -> Estimate:
        """The estimate ``dt`` seconds on (never backwards: a negative Δt is taken as 0)."""
        if not dt > 0.0:
            return self.copy()
        x0, x1, x2, x3 = self.x
        (p00, p01, p02, p03, _, p11, p12, p13, _, _, p22, p23, _, _, _, p33) = self.p
        # F·P·Fᵀ written out (P symmetric; F adds dt × velocity to position), plus Q.
        dt2 = dt * dt
        qpp, qpv, qvv = q * dt2 * dt / 3.0, q * dt2 / 2.0, q * dt
        a00 = p00 + 2.0 * dt * p02 + dt2 * p22 + qpp
        a11 = p11 + 2.0 * dt * p13 + dt2 * p33 + qpp
        a01 = p01 + dt * (p03 + p12) + dt2 * p23
        a02 = p02 + dt * p22 + qpv
        a03 = p03 + dt * p23
        a12 = p12 + dt * p23
        a13 = p13 + dt * p33 + qpv
        a22, a23, a33 = p22 + qvv, p23, p33 + qvv
        return Estimate(
            [x0 + dt * x2, x1 + dt * x3, x2, x3],
            [a00, a01, a02, a03, a01, a11, a12, a13, a02, a12, a22, a23, a03, a13, a23, a33],
        )

    def position_var_max_after(self, dt: float, q: float) -> float:
        """``predicted(dt, q).position_var_max``, without building the estimate."""
        if not dt > 0.0:
            return self.position_var_max
        p = self.p
        dt2 = dt * dt
        qpp = q * dt2 * dt / 3.0
        a = p[0] + 2.0 * dt * p[2] + dt2 * p[10] + qpp
        d = p[5] + 2.0 * dt * p[7] + dt2 * p[15] + qpp
        b = p[1] + dt * (p[3] + p[6]) + dt2 * p[11]
        return 0.5 * (a + d) + math.sqrt(0.25 * (a - d) ** 2 + b * b)

    def innovation(
        self, ze: float, zn: float, r00: float, r01: float, r11: float, pair: tuple[int, int]
    ) -> Innovation:
        """The measurement (ze, zn) of components ``pair`` with covariance R, against this."""
        i, j = pair
        p = self.p
        return Innovation(
            ze - self.x[i],
            zn - self.x[j],
            p[5 * i] + r00,
            p[4 * i + j] + r01,
            p[5 * j] + r11,
        )

    def update(self, inn: Innovation, pair: tuple[int, int]) -> None:
        """Fold in a measurement of components ``pair`` (``innovation``'s result)."""
        det = inn.det
        if not det > 0.0:
            return
        i, j = pair
        p = self.p
        si00, si01, si11 = inn.s11 / det, -inn.s01 / det, inn.s00 / det
        # P·Hᵀ is columns i and j of P; as P is symmetric, H·P is the same numbers as rows.
        c0, c1, c2, c3 = p[i], p[4 + i], p[8 + i], p[12 + i]
        d0, d1, d2, d3 = p[j], p[4 + j], p[8 + j], p[12 + j]
        # K = P·Hᵀ·S⁻¹ (4×2), columns k and l.
        k0, k1, k2, k3 = (c0 * si00 + d0 * si01, c1 * si00 + d1 * si01,
                          c2 * si00 + d2 * si01, c3 * si00 + d3 * si01)  # fmt: skip
        l0, l1, l2, l3 = (c0 * si01 + d0 * si11, c1 * si01 + d1 * si11,
                          c2 * si01 + d2 * si11, c3 * si01 + d3 * si11)  # fmt: skip
        ye, yn = inn.ye, inn.yn
        x = self.x
        x[0] += k0 * ye + l0 * yn
        x[1] += k1 * ye + l1 * yn
        x[2] += k2 * ye + l2 * yn
        x[3] += k3 * ye + l3 * yn
        # P ← P − K·(H·P): the upper triangle, mirrored (exactly symmetric).
        n00 = p[0] - k0 * c0 - l0 * d0
        n01 = p[1] - k0 * c1 - l0 * d1
        n02 = p[2] - k0 * c2 - l0 * d2
        n03 = p[3] - k0 * c3 - l0 * d3
        n11 = p[5] - k1 * c1 - l1 * d1
        n12 = p[6] - k1 * c2 - l1 * d2
        n13 = p[7] - k1 * c3 - l1 * d3
        n22 = p[10] - k2 * c2 - l2 * d2
        n23 = p[11] - k2 * c3 - l2 * d3
        n33 = p[15] - k3 * c3 - l3 * d3
        self.p = [n00, n01, n02, n03, n01, n11, n12, n13, n02, n12, n22, n23, n03, n13, n23, n33]

    def update_speed(self, ue: float, un: float, speed: float, r: float) -> None:
        """Pull the state towards a speed ``speed`` along the unit vector (ue, un) as a
        measurement of variance ``r`` would, without taking its information: the covariance is
        left as it was. A prior on how fast a class goes (the tracker's speed limit) says
        nothing of where this target is heading, and must not make a velocity drawn from a
        few noisy fixes look certain."""
        p = self.p
        # h = (0, 0, ue, un); P·hᵀ is ue × column 2 + un × column 3.
        ph = [p[4 * row + 2] * ue + p[4 * row + 3] * un for row in range(4)]
        s = ph[2] * ue + ph[3] * un + r
        if not s > 0.0:
            return
        y = speed - (self.x[2] * ue + self.x[3] * un)
        k = [v / s for v in ph]
        for row in range(4):
            self.x[row] += k[row] * y

    def shift(self, east_m: float, north_m: float) -> None:
        """Move the anchor by (east, north): positions become relative to the new anchor."""
        self.x[0] -= east_m
        self.x[1] -= north_m

    @property
    def position_var(self) -> float:
        """Mean per-axis position variance (m²), (P₀₀ + P₁₁)/2."""
        return 0.5 * (self.p[0] + self.p[5])

    @property
    def position_var_max(self) -> float:
        """Largest eigenvalue of the position block (m²)."""
        a, b, d = self.p[0], self.p[1], self.p[5]
        return 0.5 * (a + d) + math.sqrt(0.25 * (a - d) ** 2 + b * b)

    @property
    def velocity_sigma(self) -> float:
        """RMS per-axis velocity σ (m/s), √((P₂₂ + P₃₃)/2)."""
        return math.sqrt(max(0.0, 0.5 * (self.p[10] + self.p[15])))
