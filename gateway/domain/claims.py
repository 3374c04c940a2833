"""The claims ledger: each figure the platform relies on, and the computation that checks it.

The claims are data (``claims.yaml``: id, what, formula, inputs, expected value, tolerance,
unit, source, notes); this module holds the named computations they refer to, each calling
the same domain function the pipeline uses, so a claim can only hold if the SDK computes it.
Nothing here returns an expected value. The ledger is validated when loaded: a claim naming
an unknown computation, or inputs its computation does not take, is a ``ClaimsError``.
"""

from __future__ import annotations

import inspect
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cache
from importlib.resources import files
from types import MappingProxyType
from typing import Any

import yaml

from gateway.domain import energy, geodesy, hopping, radio, sidc, targeting, terrain
from gateway.errors import GatewayError

__all__ = [
    "COMPUTATIONS",
    "Claim",
    "ClaimResult",
    "ClaimsError",
    "Value",
    "evaluate",
    "load_claims",
    "parse_claims",
]

#: What a claim states: a number, a yes/no, or a code (SIDC, MGRS).
Value = float | bool | str


class ClaimsError(GatewayError, ValueError):
    """Raised when the ledger is malformed; the message names the claim and the field."""


def _coverage_ratio(low_m: float, high_m: float, fov_deg: float) -> float:
    return radio.coverage_km2(high_m, fov_deg) / radio.coverage_km2(low_m, fov_deg)


def _climb_penalty_db(low_m: float, high_m: float, ground_range_m: float) -> float:
    budget = radio.LinkBudget()
    low = radio.slant_range_m(ground_range_m, low_m)
    high = radio.slant_range_m(ground_range_m, high_m)
    return budget.received_dbm(low) - budget.received_dbm(high)


def _received_dbm(distance_m: float, **budget: float) -> float:
    return radio.LinkBudget(**budget).received_dbm(distance_m)


def _margin_db(distance_m: float, **budget: float) -> float:
    return radio.LinkBudget(**budget).margin_db(distance_m)


def _cep_of_budget(sources_m: Mapping[str, float], fraction: float) -> float:
    return targeting.cep(targeting.combined_sigma(sources_m.values()), fraction)


def _endurance_min(ew_mode: str, irradiance_w_m2: float) -> float:
    """Endurance of the default profile on its full usable pack."""
    profile = energy.EnergyProfile()
    return energy.endurance_remaining_min(
        profile.battery_usable_wh, profile, energy.EwMode(ew_mode), irradiance_w_m2
    )


def _solar_nordic_summer_w() -> float:
    profile = energy.EnergyProfile()
    return energy.solar_w(profile, profile.nordic_summer_irradiance_w_m2)


def _sidc_2525c(object_class: str, hostility: sidc.Hostility) -> str:
    return sidc.symbol_codes(object_class, hostility).sidc_2525c


def _mgrs(lat_deg: float, lon_deg: float, precision_m: geodesy.MgrsPrecision) -> str:
    return geodesy.to_mgrs(lat_deg, lon_deg, precision_m)


COMPUTATIONS: Mapping[str, Callable[..., Value]] = MappingProxyType(
    {
        "agl_sigma": terrain.agl_sigma,
        "beats_reactive_jammer": hopping.beats_reactive_jammer,
        "cep_factor": targeting.cep_factor,
        "cep_of_budget": _cep_of_budget,
        "climb_penalty_db": _climb_penalty_db,
        "coverage_km2": radio.coverage_km2,
        "coverage_ratio": _coverage_ratio,
        "endurance_min": _endurance_min,
        "fspl_db": radio.fspl_db,
        "hops_per_second": hopping.hops_per_second,
        "margin_db": _margin_db,
        "mgrs": _mgrs,
        "received_dbm": _received_dbm,
        "sidc_2525c": _sidc_2525c,
        "solar_nordic_summer_w": _solar_nordic_summer_w,
    }
)


@dataclass(frozen=True)
class Claim:
    """One entry of the ledger; ``compute`` names its computation in ``COMPUTATIONS``."""

    id: str
    what: str
    formula: str
    compute: str
    inputs: Mapping[str, Any]
    expected: Value
    tolerance: float
    unit: str
    source: str
    notes: str = ""

    @property
    def function(self) -> Callable[..., Value]:
        """The computation this claim names."""
        return COMPUTATIONS[self.compute]


@dataclass(frozen=True)
class ClaimResult:
    """A claim and what the SDK computed for it (``error`` if the computation refused)."""

    claim: Claim
    value: Value | None
    error: str | None = field(default=None)

    @property
    def ok(self) -> bool:
        """True if the computed value matches: within tolerance for numbers, else equal."""
        expected, value = self.claim.expected, self.value
        if value is None:
            return False
        if isinstance(expected, bool | str) or isinstance(value, bool | str):
            return type(value) is type(expected) and value == expected
        return math.isfinite(value) and abs(value - expected) <= self.claim.tolerance


_LOOKS_NUMERIC = re.compile(r"^[-+]?[0-9.]+[eE][-+]?[0-9]+$")
_FIELDS = {f.name for f in Claim.__dataclass_fields__.values()}
_REQUIRED = _FIELDS - {"notes"}


def parse_claims(text: str) -> tuple[Claim, ...]:
    """Claims from ledger YAML, validated; ``ClaimsError`` names the first bad claim."""
    entries = yaml.safe_load(text)
    if not isinstance(entries, list):
        raise ClaimsError("the ledger must be a list of claims")
    claims: list[Claim] = []
    for index, entry in enumerate(entries):
        where = f"claim {index + 1}"
        if not isinstance(entry, dict):
            raise ClaimsError(f"{where}: expected a mapping, found {entry!r}")
        where = f"claim {entry.get('id', index + 1)}"
        if unknown := set(entry) - _FIELDS:
            raise ClaimsError(f"{where}: unknown field(s) {', '.join(sorted(unknown))}")
        if missing := _REQUIRED - set(entry):
            raise ClaimsError(f"{where}: missing field(s) {', '.join(sorted(missing))}")
        claim = Claim(**{**entry, "inputs": MappingProxyType(dict(entry["inputs"] or {}))})
        _check(where, claim)
        if any(c.id == claim.id for c in claims):
            raise ClaimsError(f"{where}: the id is used twice")
        claims.append(claim)
    return tuple(claims)


def _check(where: str, claim: Claim) -> None:
    if claim.compute not in COMPUTATIONS:
        raise ClaimsError(f"{where}: no computation named {claim.compute!r}")
    try:
        inspect.signature(claim.function).bind(**claim.inputs)
    except TypeError as exc:
        raise ClaimsError(f"{where}: inputs do not fit {claim.compute}: {exc}") from exc
    for key, value in claim.inputs.items():
        if isinstance(value, str) and _LOOKS_NUMERIC.match(value):
            # PyYAML follows YAML 1.1, where 2.4e9 (no dot, no sign) is text, not a number.
            raise ClaimsError(f"{where}: input {key} is the text {value!r}; write e.g. 2.4e+9")
    expected: object = claim.expected  # as YAML gave it, whatever the annotation says
    tolerance: object = claim.tolerance
    if not isinstance(expected, int | float | str):
        raise ClaimsError(f"{where}: expected must be a number, true/false or text")
    if not (isinstance(tolerance, int | float) and tolerance >= 0):
        raise ClaimsError(f"{where}: tolerance must be a number at least 0")
    if isinstance(expected, bool | str) and tolerance != 0:
        raise ClaimsError(f"{where}: true/false and text must match exactly (tolerance 0)")


@cache
def load_claims() -> tuple[Claim, ...]:
    """The ledger shipped with the package (``gateway/domain/claims.yaml``)."""
    return parse_claims(files("gateway.domain").joinpath("claims.yaml").read_text("utf-8"))


def evaluate(claim: Claim) -> ClaimResult:
    """Compute ``claim`` from its inputs. A computation that refuses its inputs (a
    ``ValueError``, which every domain error is) gives a failed result, not an exception.
    """
    try:
        value: object = claim.function(**claim.inputs)
    except (ValueError, ArithmeticError) as exc:
        return ClaimResult(claim, None, f"{type(exc).__name__}: {exc}")
    if isinstance(value, bool | str | float):
        return ClaimResult(claim, value)
    if isinstance(value, int):
        return ClaimResult(claim, float(value))
    return ClaimResult(claim, None, f"{claim.compute} returned {type(value).__name__}")
