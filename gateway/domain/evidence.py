"""Dempster-Shafer evidence over a frame of object classes, with an explicit ignorance mass.

A sensor's report is a mass function: belief committed to sets of classes (``{"uav"}``, or
``{"uav", "loitering_munition"}`` when it cannot tell them apart), the rest left on the whole
frame (ignorance, "it could be anything"). ``combine`` is Dempster's rule: masses multiply over
intersecting sets, the mass falling on empty intersections is the *conflict* K, and the rest
is renormalised by 1 − K. Total conflict (K = 1: the sources exclude each other) has no
combination and raises ``TotalConflict``. The fusion processor reports K on each track.

The seed's figure: EO 0.80 and IR 0.75 on AIR_MUNITION combine to 1 − 0.20 × 0.25 = 0.95.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from gateway.errors import GatewayError

__all__ = ["MassFunction", "TotalConflict", "combine", "simple_support"]

#: Below this a mass (or 1 − K) is taken as zero: floating-point dust is not evidence.
EPSILON = 1e-12


class TotalConflict(GatewayError, ValueError):
    """Raised when two bodies of evidence exclude each other (conflict K = 1)."""


@dataclass(frozen=True, slots=True)
class MassFunction:
    """Masses on non-empty subsets of ``frame``; they sum to 1. Build with ``simple_support``."""

    frame: frozenset[str]
    masses: Mapping[frozenset[str], float]

    def __post_init__(self) -> None:
        total = sum(self.masses.values())
        if abs(total - 1.0) > 1e-9:
            raise ValueError(f"masses must sum to 1, found {total!r}")
        for focal, mass in self.masses.items():
            if not focal or not focal <= self.frame:
                raise ValueError(f"focal set {sorted(focal)} is empty or outside the frame")
            if mass < 0:
                raise ValueError(f"mass of {sorted(focal)} is negative: {mass!r}")

    @property
    def ignorance(self) -> float:
        """The mass left on the whole frame."""
        return self.masses.get(self.frame, 0.0)

    def belief(self, classes: Iterable[str]) -> float:
        """Bel(A): the mass that certainly supports one of ``classes``."""
        wanted = frozenset(classes)
        return sum(m for focal, m in self.masses.items() if focal <= wanted)

    def plausibility(self, classes: Iterable[str]) -> float:
        """Pl(A): the mass that does not exclude ``classes``."""
        wanted = frozenset(classes)
        return sum(m for focal, m in self.masses.items() if focal & wanted)

    def pignistic(self) -> dict[str, float]:
        """Each class's betting probability: every focal set's mass shared evenly inside it."""
        share = dict.fromkeys(sorted(self.frame), 0.0)
        for focal, mass in self.masses.items():
            for name in focal:
                share[name] += mass / len(focal)
        return share

    def best(self) -> tuple[str, float]:
        """The class with the highest pignistic probability, and its belief."""
        probabilities = self.pignistic()
        name = max(sorted(probabilities), key=lambda c: probabilities[c])
        return name, self.belief({name})


def simple_support(frame: Iterable[str], classes: Iterable[str], support: float) -> MassFunction:
    """``support`` on ``classes`` (one or several) and 1 − ``support`` left as ignorance."""
    whole = frozenset(frame)
    focal = frozenset(classes)
    if not 0.0 <= support <= 1.0:
        raise ValueError(f"support must be within 0..1, found {support!r}")
    if not focal or not focal <= whole:
        raise ValueError(f"classes {sorted(focal)} are empty or outside the frame")
    masses: dict[frozenset[str], float] = {}
    if support > 0:
        masses[focal] = support
    if support < 1 or focal == whole:
        masses[whole] = masses.get(whole, 0.0) + (1.0 - support)
    return MassFunction(whole, masses)


def combine(a: MassFunction, b: MassFunction) -> tuple[MassFunction, float]:
    """Dempster's rule: the combined masses and the conflict K (0 ≤ K < 1).

    Raises ``ValueError`` for different frames and ``TotalConflict`` when K = 1.
    """
    if a.frame != b.frame:
        raise ValueError("mass functions over different frames cannot be combined")
    joint: dict[frozenset[str], float] = {}
    conflict = 0.0
    for focal_a, mass_a in a.masses.items():
        for focal_b, mass_b in b.masses.items():
            product = mass_a * mass_b
            both = focal_a & focal_b
            if both:
                joint[both] = joint.get(both, 0.0) + product
            else:
                conflict += product
    agreement = 1.0 - conflict
    if agreement <= EPSILON:
        raise TotalConflict("the two reports exclude each other (conflict K = 1)")
    masses = {focal: m / agreement for focal, m in joint.items() if m / agreement > EPSILON}
    # Renormalise away the rounding of the division so the masses sum to 1 exactly enough.
    total = sum(masses.values())
    return MassFunction(a.frame, {f: m / total for f, m in masses.items()}), conflict
