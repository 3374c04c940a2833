"""Frequency-hopping plans for the AD9361 transceiver's fastlock profiles.

The AD9361 stores 8 fastlock profiles per synthesizer (pre-calibrated settings it can recall
without a VCO calibration), tunes 70 MHz to 6 GHz and has at most 56 MHz of RF bandwidth. A
hop plan puts one centre frequency in each slot it uses and cycles through them. With a dwell
time t on each channel the radio hops 1/t times per second. It outruns a reactive (follower)
jammer, which must detect a transmission and retune before it can jam it, when it leaves each
channel first: dwell < the jammer's reaction time.

Recalling a profile skips the VCO calibration but not the PLL settling, about 15 µs on the
AD9361 (Analog Devices, "TDD mode switching time"). A single synthesizer therefore hops at
most 1/(dwell + 15 µs) times per second; the 1/dwell rate needs the settling hidden, e.g. by
alternating between two synthesizers. ``hops_per_second`` takes the settling as a parameter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gateway.errors import GatewayError

__all__ = [
    "AD9361_MAX_BW_HZ",
    "AD9361_PLL_SETTLE_S",
    "AD9361_RANGE_HZ",
    "FASTLOCK_SLOTS",
    "HopPlan",
    "HopPlanError",
    "beats_reactive_jammer",
    "hops_per_second",
]

FASTLOCK_SLOTS = 8
AD9361_RANGE_HZ = (70e6, 6e9)
AD9361_MAX_BW_HZ = 56e6
#: RF PLL lock time after a fastlock recall, seconds (ADI's figure, any clock rate).
AD9361_PLL_SETTLE_S = 15e-6


class HopPlanError(GatewayError, ValueError):
    """Raised for a hop plan the AD9361 cannot run; the message names the offending value."""


def hops_per_second(dwell_s: float, settle_s: float = 0.0) -> float:
    """Hops per second for ``dwell_s`` seconds on each channel plus ``settle_s`` per retune."""
    if not (dwell_s > 0 and math.isfinite(dwell_s)):
        raise HopPlanError(f"dwell must be a positive number of seconds, found {dwell_s}")
    if not settle_s >= 0:
        raise HopPlanError(f"settling time must be at least 0 s, found {settle_s}")
    return 1.0 / (dwell_s + settle_s)


def beats_reactive_jammer(dwell_s: float, jammer_reaction_s: float) -> bool:
    """True if the radio leaves each channel before a follower jammer can react (seconds)."""
    return dwell_s < jammer_reaction_s


@dataclass(frozen=True)
class HopPlan:
    """Up to 8 centre frequencies (Hz, one per fastlock slot), a bandwidth (Hz), a dwell (s)
    and the synthesizer settling time between hops (s; 0 when hidden by a second synthesizer).

    Validated on construction; ``HopPlanError`` names what the AD9361 cannot do.
    """

    frequencies_hz: tuple[float, ...]
    bandwidth_hz: float
    dwell_s: float
    settle_s: float = 0.0

    def __post_init__(self) -> None:
        low, high = AD9361_RANGE_HZ
        if not 1 <= len(self.frequencies_hz) <= FASTLOCK_SLOTS:
            raise HopPlanError(
                f"the AD9361 has {FASTLOCK_SLOTS} fastlock slots, found "
                f"{len(self.frequencies_hz)} frequencies"
            )
        for f in self.frequencies_hz:
            if not low <= f <= high:
                raise HopPlanError(f"{f / 1e6:.1f} MHz is outside 70 MHz to 6 GHz")
        if not 0 < self.bandwidth_hz <= AD9361_MAX_BW_HZ:
            raise HopPlanError(
                f"bandwidth {self.bandwidth_hz / 1e6:.1f} MHz is not within 0 to 56 MHz"
            )
        hops_per_second(self.dwell_s, self.settle_s)

    @property
    def hops_per_second(self) -> float:
        """Hop rate of this plan (hops/s), counting the settling time."""
        return hops_per_second(self.dwell_s, self.settle_s)

    def beats_reactive_jammer(self, jammer_reaction_s: float) -> bool:
        """True if each dwell ends before a jammer reacting in ``jammer_reaction_s`` can."""
        return beats_reactive_jammer(self.dwell_s, jammer_reaction_s)
