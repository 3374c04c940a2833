"""Symbols of own airframes and detected objects: the CoT type and the 2525C/2525D codes.

Both tables are data. Own airframes come from ``gateway/data/cot_types.yaml`` by MAVLink
``MAV_TYPE`` (air, ground, sea surface or subsurface, and the kind of vehicle); detected
object classes from ``gateway/domain/sidc.yaml`` (the project's class table, with the
configurable loitering-munition choice), and a class neither table knows is drawn as an
unspecified ground object of its affiliation. A track that already carries a 2525C
letter SIDC is drawn from that SIDC.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cache
from typing import Literal

import yaml

from gateway.domain.geoid import DATA_DIR
from gateway.domain.sidc import Hostility, classes, symbol_codes

__all__ = [
    "LoiteringMunition",
    "Symbol",
    "cot_type_from_sidc",
    "load_tables",
    "object_symbol",
    "own_symbol",
]

LoiteringMunition = Literal["uav_attack", "missile"]

_AFFILIATION: dict[str, str] = {
    "hostile": "h",
    "suspect": "s",
    "unknown": "u",
    "friend": "f",
    "neutral": "n",
}
_C_IDENTITY = {"h": "H", "s": "S", "u": "U", "f": "F", "n": "N"}
_D_IDENTITY = {"h": "6", "s": "5", "u": "1", "f": "3", "n": "4"}
# 2525C exercise identities map to the real-world CoT affiliations (mgrs_sidc.md).
_EXERCISE = {"G": "p", "W": "u", "M": "a", "D": "f", "L": "n"}
_LETTER_SIDC = re.compile(r"[SIOEGW][PUAFNSHJKOGWMDL][PAGSUFXZ][A-Z-][A-Z0-9-]{6}[A-Z0-9*-]{5}")


@dataclass(frozen=True, slots=True)
class Symbol:
    """How one thing is drawn: CoT type, 2525C letter SIDC, 2525D number SIDC."""

    cot_type: str
    sidc_2525c: str
    sidc_2525d: str


@cache
def _table() -> dict[str, object]:
    text = (DATA_DIR / "cot_types.yaml").read_text(encoding="utf-8")
    data: dict[str, object] = yaml.safe_load(text)
    return data


def _symbol(row: object) -> Symbol:
    if not isinstance(row, dict):
        raise TypeError(f"cot_types.yaml: expected a mapping, found {row!r}")
    return Symbol(str(row["cot"]), str(row["sidc_2525c"]), str(row["sidc_2525d"]))


@cache
def _own_by_mav_type() -> tuple[dict[int, Symbol], Symbol, Symbol]:
    groups = _table()["own_airframes"]
    if not isinstance(groups, dict) or not groups:
        raise TypeError("cot_types.yaml: own_airframes must be a non-empty mapping")
    by_type: dict[int, Symbol] = {}
    default: Symbol | None = None
    for name, row in groups.items():
        symbol = _symbol(row)
        default = default or symbol
        for mav_type in row["mav_types"]:
            if int(mav_type) in by_type:
                raise TypeError(f"cot_types.yaml: MAV_TYPE {mav_type} is in two groups ({name})")
            by_type[int(mav_type)] = symbol
    assert default is not None  # noqa: S101 - the mapping is non-empty (checked above)
    return by_type, default, _symbol(_table()["own_unlisted"])


def load_tables() -> None:
    """Read both tables now (a sink's ``open``), not at the first event drawn.

    Parsing the YAML takes milliseconds: the first detection of a run would wait for it.
    """
    _own_by_mav_type()
    _symbol(_table()["unknown_class"])
    classes()  # the class table (``gateway.domain.sidc``)


def own_symbol(mav_type: int | None) -> Symbol:
    """The friendly symbol of an own airframe from its ``MAV_TYPE``.

    None (no HEARTBEAT yet) is the fleet's own kind, the table's first group (fixed wing); a
    MAV_TYPE the table does not list is a friendly air track of unspecified kind.
    """
    by_type, default, unlisted = _own_by_mav_type()
    if mav_type is None:
        return default
    return by_type.get(mav_type, unlisted)


def _with_affiliation(symbol: Symbol, letter: str) -> Symbol:
    return Symbol(
        cot_type=symbol.cot_type[:2] + letter + symbol.cot_type[3:],
        sidc_2525c=symbol.sidc_2525c[0] + _C_IDENTITY[letter] + symbol.sidc_2525c[2:],
        sidc_2525d=symbol.sidc_2525d[:3] + _D_IDENTITY[letter] + symbol.sidc_2525d[4:],
    )


def object_symbol(
    object_class: str,
    hostility: Hostility,
    loitering_munition: LoiteringMunition,
    sidc: str | None = None,
) -> Symbol:
    """The symbol of a detected or tracked object of ``object_class`` with ``hostility``.

    A 15-character 2525C ``sidc`` (a track's own) decides the CoT type and the letter code.
    """
    letter = _AFFILIATION[hostility]
    try:
        codes = symbol_codes(object_class, hostility, loitering_munition=loitering_munition)
        symbol = Symbol(codes.cot_type, codes.sidc_2525c, codes.sidc_2525d)
    except KeyError:
        symbol = _with_affiliation(_symbol(_table()["unknown_class"]), letter)
    if sidc is not None and _LETTER_SIDC.fullmatch(sidc):
        symbol = Symbol(cot_type_from_sidc(sidc), sidc, symbol.sidc_2525d)
    elif sidc is not None and len(sidc) == 20 and sidc.isascii() and sidc.isdigit():
        symbol = Symbol(symbol.cot_type, symbol.sidc_2525c, sidc)
    return symbol


def cot_type_from_sidc(sidc: str) -> str:
    """The CoT atom type of a 2525C letter SIDC: ``SHGPEVAT-------`` → ``a-h-G-E-V-A-T``.

    Status, echelon, country and order of battle have no place in the type and are dropped.
    """
    identity = sidc[1]
    affiliation = _EXERCISE.get(identity, identity.lower())
    dimension = sidc[2] if sidc[2] not in "FZ" else "G"  # SOF and "unknown" are not CoT
    function = "".join(f"-{c}" for c in sidc[4:10] if c != "-")
    return f"a-{affiliation}-{dimension}{function}"
