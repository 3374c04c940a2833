"""Energy and endurance: battery energy over the power drawn, with EW load and solar input.

    endurance (min) = 60 · Wh remaining / (baseline W + EW overhead W − solar W)
    solar W         = irradiance (W/m²) · panel area (m²) · cell efficiency

The airframe's constants are an ``EnergyProfile`` (config ``airframes[].energy``). Its
defaults are chosen so that the seed's figures come out of these formulas rather than being
written down (see docs/claims.md for the reasoning behind each number):

- 800 Wh usable pack; 355 W baseline (the seed's cruise figure, EW payload idle);
- EW overhead 0 / 60 / 125 W for permissive / active / heavy, so heavy EW at night draws
  480 W and the full pack lasts 60 · 800 / 480 = 100 min (the seed's worst case);
- 0.40 m² of wing-mounted GaAs at 25 % in 460 W/m² (a typical Nordic summer day-time
  irradiance; clear-sky noon at 60° N is about 800 W/m²) gives 46 W (the seed's figure).
"""

from __future__ import annotations

import math
from enum import StrEnum
from types import MappingProxyType
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

__all__ = [
    "CELL_EFFICIENCY",
    "EnergyProfile",
    "EwMode",
    "endurance_remaining_min",
    "net_power_w",
    "solar_w",
]


class EwMode(StrEnum):
    """How hard the airframe's electronic-warfare payload works; sets its power overhead."""

    PERMISSIVE = "permissive"
    ACTIVE = "active"
    HEAVY = "heavy"


#: Cell efficiency by technology: GaAs per the integration guide (25 %); perovskite at a
#: conservative module value (20 %; record lab cells reach about 26 %).
CELL_EFFICIENCY = MappingProxyType({"gaas": 0.25, "perovskite": 0.20})


def _default_overheads() -> dict[EwMode, float]:
    return {EwMode.PERMISSIVE: 0.0, EwMode.ACTIVE: 60.0, EwMode.HEAVY: 125.0}


class EnergyProfile(BaseModel):
    """An airframe's energy constants (config ``airframes[].energy``); units in the names."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    battery_usable_wh: float = Field(
        default=800.0, gt=0, description="Usable pack energy, Wh (after the reserve)."
    )
    baseline_w: float = Field(
        default=355.0, gt=0, description="Cruise power with the EW payload idle, W."
    )
    ew_overhead_w: dict[EwMode, float] = Field(
        default_factory=_default_overheads,
        description="Extra power per EW mode, W; every mode must be given.",
    )
    panel_area_m2: float = Field(default=0.40, ge=0, description="Solar panel area, m².")
    cell: Literal["gaas", "perovskite"] = Field(
        default="gaas", description="Solar cell technology (sets the efficiency)."
    )
    nordic_summer_irradiance_w_m2: float = Field(
        default=460.0,
        ge=0,
        description="Typical day-time irradiance on the wing in a Nordic summer, W/m².",
    )

    @field_validator("ew_overhead_w")
    @classmethod
    def _every_mode(cls, value: dict[EwMode, float]) -> dict[EwMode, float]:
        missing = sorted(set(EwMode) - set(value))
        if missing:
            raise ValueError(f"missing EW overhead for {', '.join(missing)}")
        negative = sorted(mode for mode, watts in value.items() if not watts >= 0)
        if negative:
            raise ValueError(f"EW overhead must be at least 0 W for {', '.join(negative)}")
        return value

    @property
    def cell_efficiency(self) -> float:
        """Efficiency (0–1) of the profile's solar cells."""
        return CELL_EFFICIENCY[self.cell]


def solar_w(profile: EnergyProfile, irradiance_w_m2: float) -> float:
    """Solar power (W) from the panels at ``irradiance_w_m2`` (W/m², 0 at night)."""
    if not irradiance_w_m2 >= 0:
        raise ValueError(f"irradiance must be at least 0 W/m², found {irradiance_w_m2}")
    return irradiance_w_m2 * profile.panel_area_m2 * profile.cell_efficiency


def net_power_w(profile: EnergyProfile, ew_mode: EwMode, irradiance_w_m2: float = 0.0) -> float:
    """Power drawn from the battery (W): baseline plus EW overhead minus solar input."""
    return profile.baseline_w + profile.ew_overhead_w[ew_mode] - solar_w(profile, irradiance_w_m2)


def endurance_remaining_min(
    wh_remaining: float,
    profile: EnergyProfile,
    ew_mode: EwMode,
    irradiance_w_m2: float = 0.0,
) -> float:
    """Predicted minutes of flight left on ``wh_remaining`` Wh at the given EW mode and sun.

    A negative ``wh_remaining`` counts as empty. If the sun covers the whole load the
    battery does not drain and the result is ``math.inf``; callers that serialise it
    should cap it. ``ValueError`` for a NaN energy or a negative irradiance.
    """
    if math.isnan(wh_remaining):
        raise ValueError("energy remaining is NaN")
    net_w = net_power_w(profile, ew_mode, irradiance_w_m2)
    if net_w <= 0:
        return math.inf
    return 60.0 * max(wh_remaining, 0.0) / net_w
