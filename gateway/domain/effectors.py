"""Effector recommendation and deconfliction for a counter-UAS cue, from a table that is data.

``recommend(table, object_class, range_m, nearest_blue_m)`` walks the class's range bands
(``gateway/data/effectors.yaml`` by default) and returns, in order of preference, each
effector that reaches the target together with its deconfliction against the nearest
friendly unit: *clear* when that unit is beyond the effector's danger-close radius (or none is
known within it). It only ever recommends: the GUTE II operator authorises any engagement, and
nothing here or downstream can command an effector.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from importlib.resources import files
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from gateway.errors import ConfigError, ConfigIssue

__all__ = [
    "EffectorTable",
    "Recommendation",
    "check_effector_table",
    "load_effector_table",
    "recommend",
]

_FROZEN = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Effector(BaseModel):
    """One effector's reach and danger-close radius."""

    model_config = _FROZEN

    max_range_m: float = Field(gt=0)
    danger_close_m: float = Field(ge=0)


class Band(BaseModel):
    """Effectors for targets up to ``up_to_m`` from the battery, in order of preference."""

    model_config = _FROZEN

    up_to_m: float = Field(gt=0)
    effectors: tuple[str, ...] = Field(min_length=1)


class EffectorTable(BaseModel):
    """The effectors and, per class, the range bands."""

    model_config = _FROZEN

    effectors: dict[str, Effector]
    recommendations: dict[str, tuple[Band, ...]]


@dataclass(frozen=True, slots=True)
class Recommendation:
    """One effector for the operator to consider, and whether friendly units allow it."""

    effector: str
    deconfliction_clear: bool
    nearest_blue_m: float | None
    danger_close_m: float


def load_effector_table(text: str | None = None, source: str = "effectors.yaml") -> EffectorTable:
    """Parse a table (the shipped one when ``text`` is None); ``ConfigError`` if it is wrong."""
    if text is None:
        return _shipped_table()
    try:
        data: Any = yaml.safe_load(text)
        table = EffectorTable.model_validate(data)
    except (yaml.YAMLError, ValidationError) as exc:
        raise ConfigError([ConfigIssue(source, None, "(effectors)", str(exc))]) from exc
    return check_effector_table(table, source)


@cache
def _shipped_table() -> EffectorTable:
    """The shipped table, read and checked once (it is frozen, so it can be shared)."""
    text = files("gateway").joinpath("data/effectors.yaml").read_text(encoding="utf-8")
    return load_effector_table(text, "gateway/data/effectors.yaml")


def check_effector_table(table: EffectorTable, source: str) -> EffectorTable:
    """``table`` if its bands name known effectors and ascend; ``ConfigError`` otherwise."""
    problems = [
        f"recommendations.{cls}: unknown effector {name!r}"
        for cls, bands in table.recommendations.items()
        for band in bands
        for name in band.effectors
        if name not in table.effectors
    ]
    problems += [
        f"recommendations.{cls}: range bands must ascend"
        for cls, bands in table.recommendations.items()
        if [b.up_to_m for b in bands] != sorted(b.up_to_m for b in bands)
    ]
    if problems:
        raise ConfigError([ConfigIssue(source, None, "(effectors)", p) for p in problems])
    return table


def recommend(
    table: EffectorTable,
    object_class: str,
    range_m: float,
    nearest_blue_m: float | None,
    *,
    uncertainty_m: float = 0.0,
) -> list[Recommendation]:
    """The effectors to recommend for a target at ``range_m``, best first; [] if none fits.

    ``uncertainty_m`` (the track's CEP90, say) is taken off the distance to the nearest
    friendly unit before it is compared with each danger-close radius: the target may be that
    much closer to them than its reported position.
    """
    for band in table.recommendations.get(object_class, ()):
        if range_m > band.up_to_m:
            continue
        out = []
        for name in band.effectors:
            effector = table.effectors[name]
            if range_m > effector.max_range_m:
                continue
            clear = (
                nearest_blue_m is None or nearest_blue_m - uncertainty_m > effector.danger_close_m
            )
            out.append(Recommendation(name, clear, nearest_blue_m, effector.danger_close_m))
        return out
    return []
