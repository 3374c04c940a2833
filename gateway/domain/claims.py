"""The claims ledger: each figure the platform relies on, computed from its formula.

The claims are data (``claims.yaml``: id, what, formula, inputs, expected value, tolerance,
unit); this module holds only the named computations they refer to, each calling the same
domain function the pipeline uses. Nothing here returns an expected value: it is computed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from importlib.resources import files
from typing import Any

import yaml

from gateway.domain import energy, hopping, radio, sidc, targeting, terrain

__all__ = ["COMPUTATIONS", "Claim", "ClaimResult", "evaluate", "load_claims"]


def _coverage_ratio(low_m: float, high_m: float, fov_deg: float) -> float:
    return radio.coverage_km2(high_m, fov_deg) / radio.coverage_km2(low_m, fov_deg)


def _climb_penalty_db(low_m: float, high_m: float, ground_range_m: float) -> float:
    budget = radio.LinkBudget()
    low = radio.slant_range_m(ground_range_m, low_m)
    high = radio.slant_range_m(ground_range_m, high_m)
    return budget.received_dbm(low) - budget.received_dbm(high)


def _endurance_min(ew_mode: str, irradiance_w_m2: float) -> float:
    profile = energy.EnergyProfile()
    return energy.endurance_remaining_min(
        profile.battery_usable_wh, profile, energy.EwMode(ew_mode), irradiance_w_m2
    )


def _solar_nordic_summer_w() -> float:
    profile = energy.EnergyProfile()
    return energy.solar_w(profile, profile.nordic_summer_irradiance_w_m2)


def _sidc_matches(object_class: str, hostility: sidc.Hostility, expected_sidc: str) -> float:
    return float(sidc.symbol_codes(object_class, hostility).sidc_2525c == expected_sidc)


COMPUTATIONS: dict[str, Callable[..., float]] = {
    "agl_sigma": terrain.agl_sigma,
    "coverage_km2": radio.coverage_km2,
    "coverage_ratio": _coverage_ratio,
    "climb_penalty_db": _climb_penalty_db,
    "received_dbm": lambda distance_m: radio.LinkBudget().received_dbm(distance_m),
    "margin_db": lambda distance_m: radio.LinkBudget().margin_db(distance_m),
    "hops_per_second": hopping.hops_per_second,
    "beats_reactive_jammer": lambda **kw: float(hopping.beats_reactive_jammer(**kw)),
    "cep_factor": targeting.cep_factor,
    "cep_of_budget": lambda sigmas_m, fraction: targeting.cep(
        targeting.combined_sigma(sigmas_m), fraction
    ),
    "endurance_min": _endurance_min,
    "solar_nordic_summer_w": _solar_nordic_summer_w,
    "sidc_matches": _sidc_matches,
}


@dataclass(frozen=True)
class Claim:
    """One entry of the ledger."""

    id: str
    what: str
    formula: str
    compute: str
    inputs: dict[str, Any]
    expected: float
    tolerance: float
    unit: str


@dataclass(frozen=True)
class ClaimResult:
    """A claim and what the SDK computed for it."""

    claim: Claim
    value: float

    @property
    def ok(self) -> bool:
        """True if the computed value is within tolerance of the expected one."""
        return abs(self.value - self.claim.expected) <= self.claim.tolerance


@cache
def load_claims() -> tuple[Claim, ...]:
    """The ledger as shipped with the package."""
    text = files("gateway.domain").joinpath("claims.yaml").read_text(encoding="utf-8")
    return tuple(Claim(**entry) for entry in yaml.safe_load(text))


def evaluate(claim: Claim) -> ClaimResult:
    """Compute ``claim`` with its named computation and inputs."""
    return ClaimResult(claim, float(COMPUTATIONS[claim.compute](**claim.inputs)))
