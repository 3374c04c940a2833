"""Object classes to MIL-STD-2525C (15-character) and 2525D (20-digit) symbol codes.

The table is data (``sidc.yaml``); the standard identity (hostile, suspect, unknown, friend,
neutral) is substituted at position 2 (2525C) and digit 4 (2525D). Neither standard has a
loitering-munition symbol: the table offers "unmanned aircraft, attack" and "missile,
launched", chosen by ``loitering_munition`` (the brigade's symbology SOP decides).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from importlib.resources import files
from typing import Literal

import yaml

__all__ = ["Hostility", "SymbolCodes", "classes", "symbol_codes"]

Hostility = Literal["hostile", "suspect", "unknown", "friend", "neutral"]
_C_IDENTITY = {"hostile": "H", "suspect": "S", "unknown": "U", "friend": "F", "neutral": "N"}
_D_IDENTITY = {"hostile": "6", "suspect": "5", "unknown": "1", "friend": "3", "neutral": "4"}


@dataclass(frozen=True, slots=True)
class SymbolCodes:
    """The symbol of one object: 2525C letter code, 2525D number, CoT type."""

    sidc_2525c: str
    sidc_2525d: str
    cot_type: str


@cache
def _table() -> dict[str, dict[str, str]]:
    text = files("gateway.domain").joinpath("sidc.yaml").read_text(encoding="utf-8")
    data: dict[str, dict[str, str]] = yaml.safe_load(text)
    return data


def classes() -> frozenset[str]:
    """The object classes the table knows."""
    return frozenset(_table())


def symbol_codes(
    object_class: str,
    hostility: Hostility = "hostile",
    *,
    loitering_munition: Literal["uav_attack", "missile"] = "uav_attack",
) -> SymbolCodes:
    """Codes for ``object_class``; ``KeyError`` names the class if the table lacks it."""
    key = object_class
    if object_class == "loitering_munition":
        key = f"loitering_munition_{loitering_munition}"
    try:
        row = _table()[key]
    except KeyError:
        raise KeyError(f"no symbol for object class {object_class!r}") from None
    c, d = row["c"], row["d"]
    affiliation = {"hostile": "h", "suspect": "s", "unknown": "u", "friend": "f", "neutral": "n"}
    return SymbolCodes(
        sidc_2525c=c[0] + _C_IDENTITY[hostility] + c[2:],
        sidc_2525d=d[:3] + _D_IDENTITY[hostility] + d[4:],
        cot_type="a-" + affiliation[hostility] + row["cot"][3:],
    )
