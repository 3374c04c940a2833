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
        dt = max(0.0, dt)
        x, p = self.x, self.p
        if dt == 0.0:
            return self.copy()
        nx = [x[0] + dt * x[2], x[1] + dt * x[3], x[2], x[3]]
        # A = F·P: rows 0 and 1 gain dt × rows 2 and 3.
        a = list(p)
        for j in range(4):
            a[j] += dt * p[8 + j]
            a[4 + j] += dt * p[12 + j]
        # F·P·Fᵀ: columns 0 and 1 gain dt × columns 2 and 3.
        for i in range(4):
            a[4 * i] += dt * a[4 * i + 2]
            a[4 * i + 1] += dt * a[4 * i + 3]
        qpp, qpv, qvv = q * dt**3 / 3.0, q * dt * dt / 2.0, q * dt
        a[0] += qpp
        a[5] += qpp
        a[2] += qpv
        a[8] += qpv
        a[7] += qpv
        a[13] += qpv
        a[10] += qvv
        a[15] += qvv
        return Estimate(nx, a)

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
        # K = P·Hᵀ·S⁻¹ (4×2); P·Hᵀ is columns i and j of P.
        k = []
        for r in range(4):
            ci, cj = p[4 * r + i], p[4 * r + j]
            k.append((ci * si00 + cj * si01, ci * si01 + cj * si11))
        for r in range(4):
            self.x[r] += k[r][0] * inn.ye + k[r][1] * inn.yn
        # P ← P − K·(H·P), H·P being rows i and j of P; then made exactly symmetric.
        hp_i, hp_j = p[4 * i : 4 * i + 4], p[4 * j : 4 * j + 4]
        new = [
            p[4 * r + c] - k[r][0] * hp_i[c] - k[r][1] * hp_j[c] for r in range(4) for c in range(4)
        ]
        for r in range(4):
            for c in range(r + 1, 4):
                mean = 0.5 * (new[4 * r + c] + new[4 * c + r])
                new[4 * r + c] = new[4 * c + r] = mean
        self.p = new

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
