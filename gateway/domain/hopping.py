"""Frequency-hopping plans for the AD9361 transceiver's fastlock profiles.

The AD9361 stores 8 fastlock profiles (pre-calibrated synthesizer settings), tunes 70 MHz to
6 GHz and has at most 56 MHz of RF bandwidth. A hop pattern cycles through the profiles; with
a dwell time t the radio hops 1/t times per second. It outruns a reactive (follower) jammer
when it leaves a channel before the jammer can detect it and retune: dwell < reaction time.
"""

from __future__ import annotations

from dataclasses import dataclass

from gateway.errors import GatewayError

__all__ = [
    "AD9361_MAX_BW_HZ",
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


class HopPlanError(GatewayError, ValueError):
    """Raised for a hop plan the AD9361 cannot run."""


def hops_per_second(dwell_s: float) -> float:
    """Hops per second for a dwell time per channel."""
    if dwell_s <= 0:
        raise HopPlanError(f"dwell must be positive, found {dwell_s} s")
    return 1.0 / dwell_s


def beats_reactive_jammer(dwell_s: float, jammer_reaction_s: float) -> bool:
    """True if the radio leaves each channel before a follower jammer can react."""
    return dwell_s < jammer_reaction_s


@dataclass(frozen=True)
class HopPlan:
    """Up to 8 centre frequencies (one per fastlock slot), a bandwidth and a dwell time."""

    frequencies_hz: tuple[float, ...]
    bandwidth_hz: float
    dwell_s: float

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
            raise HopPlanError(f"bandwidth {self.bandwidth_hz / 1e6:.1f} MHz exceeds 56 MHz")
        hops_per_second(self.dwell_s)

    @property
    def hops_per_second(self) -> float:
        """Hop rate of this plan."""
        return hops_per_second(self.dwell_s)
