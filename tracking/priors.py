"""Per-class motion priors: a plausible top speed and a manoeuvring acceleration.

Read from ``tracking/classes.yaml`` (package data) or a mapping an operator gives. A class the
table lacks takes the ``other`` row. The speed limit is a *prior*: it sets how wide a new
track's velocity uncertainty starts (σ = the limit per axis, so a second detection of a target
at full speed still falls in the gate) and the tracker pulls an estimate beyond it back along
its course; it never clamps what is published.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from importlib.resources import files

import yaml

__all__ = ["ClassPrior", "Priors", "load_priors"]

_OTHER = "other"


@dataclass(frozen=True, slots=True)
class ClassPrior:
    """One class's motion prior."""

    max_speed_mps: float
    accel_mps2: float

    @property
    def q(self) -> float:
        """Process-noise spectral density per axis (m²/s³): accel² × 1 s."""
        return self.accel_mps2 * self.accel_mps2


class Priors:
    """Class name → ``ClassPrior``; ``other`` for any name not listed."""

    def __init__(self, table: Mapping[str, ClassPrior]) -> None:
        if _OTHER not in table:
            raise ValueError(f"motion priors need an {_OTHER!r} row")
        self._table = dict(table)
        self.fastest_mps = max(p.max_speed_mps for p in table.values())

    def __getitem__(self, name: str) -> ClassPrior:
        return self._table.get(name) or self._table[_OTHER]

    def names(self) -> list[str]:
        """The classes listed, sorted."""
        return sorted(self._table)


def _row(name: str, value: object) -> ClassPrior:
    if not isinstance(value, Mapping):
        raise ValueError(f"motion prior {name!r}: expected a mapping, found {value!r}")
    try:
        speed, accel = float(value["max_speed_mps"]), float(value["accel_mps2"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"motion prior {name!r}: {exc!r}") from None
    for label, number in (("max_speed_mps", speed), ("accel_mps2", accel)):
        if not (math.isfinite(number) and number > 0):
            raise ValueError(f"motion prior {name!r}: {label} must be > 0, found {number!r}")
    return ClassPrior(speed, accel)


@cache
def _shipped() -> dict[str, ClassPrior]:
    text = files("tracking").joinpath("classes.yaml").read_text(encoding="utf-8")
    raw = yaml.safe_load(text)
    return {str(name): _row(str(name), value) for name, value in raw.items()}


def load_priors(overrides: Mapping[str, object] | None = None) -> Priors:
    """The shipped table, with ``overrides`` (class → {max_speed_mps, accel_mps2}) on top."""
    table = dict(_shipped())
    for name, value in (overrides or {}).items():
        table[name] = _row(name, value)
    return Priors(table)
