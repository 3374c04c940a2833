"""Target location error: combining independent error sources, and circular error probable.

Independent 1σ errors add as a root-sum-square. For a circular normal distribution with
per-axis standard deviation σ, the radius holding a fraction p of the points is
σ·√(−2·ln(1−p)) (the Rayleigh quantile): CEP50 = √(2 ln 2)·σ ≈ 1.1774 σ and
CEP90 = √(2 ln 10)·σ ≈ 2.1460 σ. The error sources of a target fix (SLAM position, bounding
box, camera calibration, attitude) are taken as per-axis 1σ values in metres.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

__all__ = [
    "CEP50_FACTOR",
    "CEP90_FACTOR",
    "cep",
    "cep50_m",
    "cep90_m",
    "cep_factor",
    "combined_sigma",
]


def cep_factor(fraction: float) -> float:
    """Radius, in units of σ, that holds ``fraction`` (0 < p < 1) of a circular normal."""
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must be between 0 and 1, found {fraction}")
    return math.sqrt(-2.0 * math.log1p(-fraction))


CEP50_FACTOR = cep_factor(0.5)
CEP90_FACTOR = cep_factor(0.9)


def combined_sigma(sigmas_m: Iterable[float]) -> float:
    """Root-sum-square (m) of independent 1σ errors given in metres."""
    values = list(sigmas_m)
    if not all(s >= 0 for s in values):  # also rejects NaN
        raise ValueError(f"sigmas must be non-negative numbers, found {values}")
    return math.sqrt(sum(s * s for s in values))


def cep(sigma_m: float, fraction: float = 0.5) -> float:
    """Radius (m) holding ``fraction`` of fixes for a per-axis σ (m); CEP50 by default."""
    return sigma_m * cep_factor(fraction)


def cep50_m(sigmas_m: Iterable[float]) -> float:
    """CEP50 (m) of a fix whose independent per-axis 1σ error sources are ``sigmas_m``."""
    return CEP50_FACTOR * combined_sigma(sigmas_m)


def cep90_m(sigmas_m: Iterable[float]) -> float:
    """CEP90 (m) of a fix whose independent per-axis 1σ error sources are ``sigmas_m``."""
    return CEP90_FACTOR * combined_sigma(sigmas_m)
