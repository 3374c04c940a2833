"""Radio link budget and sensor coverage.

Free-space path loss FSPL = 20·log10(d) + 20·log10(f) + 20·log10(4π/c) (d in m, f in Hz);
received power = transmit power + antenna gains − FSPL; margin = received − sensitivity.
The slant range from an airframe at height h above a ground station at ground range r is
√(r² + h²). A camera cone of full angle FOV at height h covers π·(h·tan(FOV/2))².
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = [
    "LinkBudget",
    "coverage_km2",
    "fspl_db",
    "received_power_dbm",
    "slant_range_m",
]

_C = 299_792_458.0


def fspl_db(distance_m: float, frequency_hz: float) -> float:
    """Free-space path loss in dB."""
    if distance_m <= 0 or frequency_hz <= 0:
        raise ValueError("distance and frequency must be positive")
    return (
        20 * math.log10(distance_m)
        + 20 * math.log10(frequency_hz)
        + 20 * math.log10(4 * math.pi / _C)
    )


def slant_range_m(ground_range_m: float, height_m: float) -> float:
    """Straight-line distance to an airframe ``height_m`` above, ``ground_range_m`` away."""
    return math.hypot(ground_range_m, height_m)


@dataclass(frozen=True)
class LinkBudget:
    """A radio link's constants. Defaults: 2.4 GHz, 30 dBm, 4 dBi each end, −102 dBm."""

    frequency_hz: float = 2.4e9
    tx_power_dbm: float = 30.0
    tx_gain_dbi: float = 4.0
    rx_gain_dbi: float = 4.0
    sensitivity_dbm: float = -102.0

    def received_dbm(self, distance_m: float) -> float:
        """Received power at ``distance_m`` in free space."""
        return received_power_dbm(self, distance_m)

    def margin_db(self, distance_m: float) -> float:
        """Received power above the receiver's sensitivity."""
        return self.received_dbm(distance_m) - self.sensitivity_dbm


def received_power_dbm(budget: LinkBudget, distance_m: float) -> float:
    """Transmit power plus both gains minus free-space loss."""
    return (
        budget.tx_power_dbm
        + budget.tx_gain_dbi
        + budget.rx_gain_dbi
        - fspl_db(distance_m, budget.frequency_hz)
    )


def coverage_km2(height_m: float, fov_deg: float) -> float:
    """Ground footprint (km²) of a nadir camera cone of full angle ``fov_deg``."""
    if not 0 < fov_deg < 180:
        raise ValueError(f"field of view must be between 0 and 180 degrees, found {fov_deg}")
    radius = height_m * math.tan(math.radians(fov_deg) / 2)
    return math.pi * radius * radius / 1e6
