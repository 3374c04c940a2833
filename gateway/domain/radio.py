"""Radio link budget and sensor coverage.

    FSPL (dB)     = 20·log10(d) + 20·log10(f) + 20·log10(4π/c)   (d in m, f in Hz)
    received dBm  = transmit dBm + transmit gain dBi + receive gain dBi − FSPL
    margin dB     = received dBm − receiver sensitivity dBm
    slant range   = √(ground range² + height²)
    footprint km² = π·(h·tan(FOV/2))² / 10⁶   (nadir camera cone of full angle FOV)

Free space is the optimistic case: it ignores terrain, the Fresnel zone, body shadowing and
cable losses, so treat a margin as an upper bound.
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

_C_MPS = 299_792_458.0


def fspl_db(distance_m: float, frequency_hz: float) -> float:
    """Free-space path loss (dB) over ``distance_m`` metres at ``frequency_hz``."""
    if not (distance_m > 0 and frequency_hz > 0):
        raise ValueError(
            f"distance and frequency must be positive, found {distance_m} m, {frequency_hz} Hz"
        )
    return 20 * math.log10(4 * math.pi * distance_m * frequency_hz / _C_MPS)


def slant_range_m(ground_range_m: float, height_m: float) -> float:
    """Straight-line distance (m) to an airframe ``height_m`` up, ``ground_range_m`` away."""
    return math.hypot(ground_range_m, height_m)


@dataclass(frozen=True)
class LinkBudget:
    """A radio link's constants.

    Defaults, which reproduce the guide's 50 km figures: 2.4 GHz, 30 dBm (1 W) transmit,
    4 dBi antennas at each end, −102 dBm receiver sensitivity.
    """

    frequency_hz: float = 2.4e9
    tx_power_dbm: float = 30.0
    tx_gain_dbi: float = 4.0
    rx_gain_dbi: float = 4.0
    sensitivity_dbm: float = -102.0

    def received_dbm(self, distance_m: float) -> float:
        """Received power (dBm) at ``distance_m`` metres in free space."""
        return received_power_dbm(self, distance_m)

    def margin_db(self, distance_m: float) -> float:
        """Received power above the receiver's sensitivity (dB) at ``distance_m``."""
        return self.received_dbm(distance_m) - self.sensitivity_dbm

    def max_range_m(self) -> float:
        """The free-space distance (m) at which the margin reaches 0 dB."""
        budget_db = self.tx_power_dbm + self.tx_gain_dbi + self.rx_gain_dbi - self.sensitivity_dbm
        return 10 ** (budget_db / 20) * _C_MPS / (4 * math.pi * self.frequency_hz)


def received_power_dbm(budget: LinkBudget, distance_m: float) -> float:
    """Transmit power plus both antenna gains minus free-space loss (dBm)."""
    return (
        budget.tx_power_dbm
        + budget.tx_gain_dbi
        + budget.rx_gain_dbi
        - fspl_db(distance_m, budget.frequency_hz)
    )


def coverage_km2(height_m: float, fov_deg: float) -> float:
    """Ground footprint (km²) of a nadir camera cone of full angle ``fov_deg`` at ``height_m``."""
    if not 0 < fov_deg < 180:
        raise ValueError(f"field of view must be between 0 and 180 degrees, found {fov_deg}")
    if not height_m >= 0:
        raise ValueError(f"height must be at least 0 m, found {height_m}")
    radius_m = height_m * math.tan(math.radians(fov_deg) / 2)
    return math.pi * radius_m * radius_m / 1e6
