"""Target location error: combining independent error sources, and circular error probable.

For a circular normal distribution with per-axis standard deviation σ, the radius holding a
fraction p of the points is σ·√(−2·ln(1−p)): CEP50 = √(2 ln 2)·σ ≈ 1.1774 σ and
CEP90 = √(2 ln 10)·σ ≈ 2.1460 σ.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

__all__ = ["CEP50_FACTOR", "CEP90_FACTOR", "cep", "cep_factor", "combined_sigma"]


def cep_factor(fraction: float) -> float:
    """Radius, in units of σ, that holds ``fraction`` (0..1) of a circular normal."""
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must be between 0 and 1, found {fraction}")
    return math.sqrt(-2.0 * math.log(1.0 - fraction))


CEP50_FACTOR = cep_factor(0.5)
CEP90_FACTOR = cep_factor(0.9)


def combined_sigma(sigmas_m: Iterable[float]) -> float:
    """Root-sum-square of independent 1σ errors, metres."""
    values = list(sigmas_m)
    if any(s < 0 or math.isnan(s) for s in values):
        raise ValueError(f"sigmas must be non-negative numbers, found {values}")
    return math.sqrt(sum(s * s for s in values))


def cep(sigma_m: float, fraction: float = 0.5) -> float:
    """Circular error probable (m) for a per-axis σ (m): CEP50 by default."""
    return sigma_m * cep_factor(fraction)
