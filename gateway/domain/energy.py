"""Energy and endurance: battery energy over power drawn, with EW load and solar input.

endurance (min) = 60 · usable Wh remaining / (baseline W + EW overhead W − solar W), and
solar W = irradiance (W/m²) · panel area (m²) · cell efficiency. The profile's documented
defaults reproduce the seed's figures: heavy EW at night gives 100 min (800 Wh over
355 + 125 W), and a Nordic summer day (460 W/m² on 0.40 m² of 25 % GaAs) gives 46 W.
"""

from __future__ import annotations

from enum import StrEnum

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["CELL_EFFICIENCY", "EnergyProfile", "EwMode", "endurance_remaining_min", "solar_w"]


class EwMode(StrEnum):
    """How hard the airframe's electronic-warfare payload works."""

    PERMISSIVE = "permissive"
    ACTIVE = "active"
    HEAVY = "heavy"


#: Cell efficiencies: GaAs per the integration guide; perovskite a conservative module value.
CELL_EFFICIENCY = {"gaas": 0.25, "perovskite": 0.20}


class EnergyProfile(BaseModel):
    """An airframe's energy constants (config ``airframes[].energy``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    battery_usable_wh: float = Field(default=800.0, gt=0, description="Usable pack energy.")
    baseline_w: float = Field(default=355.0, gt=0, description="Cruise power, EW off.")
    ew_overhead_w: dict[EwMode, float] = Field(
        default_factory=lambda: {EwMode.PERMISSIVE: 0.0, EwMode.ACTIVE: 60.0, EwMode.HEAVY: 125.0},
        description="Extra power per EW mode.",
    )
    panel_area_m2: float = Field(default=0.40, ge=0)
    cell: str = Field(default="gaas", pattern="^(gaas|perovskite)$")
    nordic_summer_irradiance_w_m2: float = Field(
        default=460.0, ge=0, description="Typical irradiance on the wing, Nordic summer day."
    )


def solar_w(profile: EnergyProfile, irradiance_w_m2: float) -> float:
    """Solar power (W) from the wing panels at ``irradiance_w_m2``."""
    if irradiance_w_m2 < 0:
        raise ValueError(f"irradiance cannot be negative, found {irradiance_w_m2}")
    return irradiance_w_m2 * profile.panel_area_m2 * CELL_EFFICIENCY[profile.cell]


def endurance_remaining_min(
    wh_remaining: float,
    profile: EnergyProfile,
    ew_mode: EwMode,
    irradiance_w_m2: float = 0.0,
) -> float:
    """Minutes of flight left; infinite if solar input covers the whole load."""
    net_w = profile.baseline_w + profile.ew_overhead_w[ew_mode] - solar_w(profile, irradiance_w_m2)
    if net_w <= 0:
        return float("inf")
    return 60.0 * max(wh_remaining, 0.0) / net_w
