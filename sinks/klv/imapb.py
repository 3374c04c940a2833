"""MISB ST 1201 IMAPB: a real number in a range [a, b] as an L-byte unsigned integer.

The scale is a power of two chosen from the range and the length, so the receiver needs
only (a, b) from the tag's definition and L from the item's length. A raw value whose top
bit is set (except the one normal value ``0x80 00 …``) is a special value: infinities,
NaNs, "below minimum" and "above maximum" (``Special``).
"""

from __future__ import annotations

import math
from enum import StrEnum

__all__ = ["Imapb", "Special"]


class Special(StrEnum):
    """A value that is not a number: what a tag's error indicator or an IMAPB code word says."""

    #: The legacy ST 0601 reserved value (``0x8000``, ``0x80000000``): out of range, off earth.
    ERROR = "error"
    BELOW_MINIMUM = "below_minimum"
    ABOVE_MAXIMUM = "above_maximum"
    POSITIVE_INFINITY = "positive_infinity"
    NEGATIVE_INFINITY = "negative_infinity"
    NAN = "nan"
    OTHER = "other"  # user-defined or reserved code words: kept, but meaningless to us


#: First byte of each special code word (the rest of the bytes zero).
_SPECIAL_FIRST_BYTE: dict[Special, int] = {
    Special.BELOW_MINIMUM: 0xE0,
    Special.ABOVE_MAXIMUM: 0xE1,
    Special.POSITIVE_INFINITY: 0xC8,
    Special.NEGATIVE_INFINITY: 0xE8,
    Special.NAN: 0xD0,
}


class Imapb:
    """The IMAPB mapping of [``minimum``, ``maximum``] onto ``length`` bytes."""

    __slots__ = ("_offset", "_scale", "length", "maximum", "minimum")

    def __init__(self, minimum: float, maximum: float, length: int) -> None:
        if not maximum > minimum or not 1 <= length <= 8:
            raise ValueError(f"IMAPB: expected minimum < maximum and length 1..8, got {length}")
        self.minimum = minimum
        self.maximum = maximum
        self.length = length
        b_pow = math.ceil(math.log2(maximum - minimum))
        d_pow = 8 * length - 1
        self._scale = 2.0 ** (d_pow - b_pow)
        # A range spanning zero gets an offset so that 0.0 maps onto an integer exactly.
        scaled_min = self._scale * minimum
        self._offset = scaled_min - math.floor(scaled_min) if minimum < 0 < maximum else 0.0

    @property
    def resolution(self) -> float:
        """The step between two neighbouring raw values (one LSB)."""
        return 1.0 / self._scale

    def encode(self, value: float | Special) -> bytes:
        """``length`` bytes for ``value``; NaN, infinities and out-of-range become code words."""
        if isinstance(value, Special):
            return self._code(value)
        if math.isnan(value):
            return self._code(Special.NAN)
        if value < self.minimum:
            return self._code(
                Special.NEGATIVE_INFINITY if math.isinf(value) else Special.BELOW_MINIMUM
            )
        if value > self.maximum:
            return self._code(
                Special.POSITIVE_INFINITY if math.isinf(value) else Special.ABOVE_MAXIMUM
            )
        raw = math.floor(self._scale * (value - self.minimum) + self._offset)
        raw = min(raw, (1 << (8 * self.length - 1)))  # the top of the range, never a code word
        return raw.to_bytes(self.length, "big")

    def decode(self, data: bytes | memoryview) -> float | Special:
        """The value of ``data`` (its length is L); a ``Special`` for a code word."""
        if len(data) != self.length:
            raise ValueError(f"IMAPB: expected {self.length} bytes, got {len(data)}")
        raw = int.from_bytes(data, "big")
        top = 1 << (8 * len(data) - 1)
        if raw & top and raw != top:
            first, rest = data[0], any(data[1:])
            for special, byte in _SPECIAL_FIRST_BYTE.items():
                if first == byte and not rest:
                    return special
            return Special.NAN if first & 0xF0 in (0xD0, 0xF0) else Special.OTHER
        return (raw - self._offset) / self._scale + self.minimum

    def _code(self, special: Special) -> bytes:
        byte = _SPECIAL_FIRST_BYTE.get(special)
        if byte is None:
            raise ValueError(f"IMAPB: {special} has no code word")
        return bytes((byte,)) + bytes(self.length - 1)
