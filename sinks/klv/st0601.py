"""MISB ST 0601 UAS Datalink Local Set: the tag table, and packets to and from tag values.

``encode(values)`` builds one packet (16-byte key, BER length, items, checksum) from
``{tag: value}``; ``decode(packet)`` checks the key, the framing and the checksum and gives
back ``{tag: value}``. Values are Python numbers in the tag's units (degrees, metres, m/s),
``str`` for text, an aware ``datetime`` for time stamps, ``bytes`` for nested sets and unknown
tags, and ``Special`` for an error indicator or an IMAPB code word.

Out-of-range inputs: a signed mapped tag (pitch, latitude, frame centre ...) is sent as its
reserved error indicator (``0x80…``); an unsigned mapped, IMAPB or integer tag is left out
of the packet (ST 0601.19 permits no IMAPB code words in its tags, and the unsigned legacy
tags have no indicator). ``decode`` still reads IMAPB code words as ``Special``, and never
interprets an item whose length does not fit its tag: it is kept as ``bytes``. Unknown tags
are skipped by their length, as the standard asks.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from functools import lru_cache
from typing import Literal

from gateway.errors import Malformed
from sinks.klv.ber import (
    UAS_LS_KEY,
    checksum,
    decode_ber_length,
    encode_ber_length,
    encode_ber_oid,
    iter_items,
)
from sinks.klv.imapb import Imapb, Special

__all__ = [
    "TAGS",
    "VERSION",
    "Tag",
    "Value",
    "decode",
    "encode",
    "resolution",
]

#: The revision we write in tag 65: ST 0601.19.
VERSION = 19

Value = float | int | str | datetime | bytes | Special
Kind = Literal["time", "text", "umap", "smap", "uint", "int", "imapb", "bytes"]

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_MAX_MICROS = (datetime(9999, 1, 1, tzinfo=UTC) - _EPOCH) // timedelta(microseconds=1)
_CHECKSUM_TAG = 1
_TRIM = " \t\r\n\x00"
_TIME_TAG = 2
_MAX_TEXT = 127


@dataclass(frozen=True, slots=True)
class Tag:
    """One ST 0601 item: its mapping (``kind``), range and nominal length in bytes.

    ``length`` is the fixed length of mapped tags, the maximum of variable ones (integers,
    IMAPB, text); ``default_length`` is what we write for IMAPB tags.
    """

    tag: int
    name: str
    kind: Kind
    length: int = 0
    low: float = 0.0
    high: float = 0.0
    default_length: int = 0


def _t(tag: int, name: str, kind: Kind, length: int = 0, low: float = 0.0, high: float = 0.0,
       default_length: int = 0) -> Tag:  # fmt: skip
    return Tag(tag, name, kind, length, low, high, default_length)


_ALT = (-900.0, 19_000.0)
_ALT_EXT = (-900.0, 40_000.0)
_CORNERS = [
    _t(26 + i, f"Offset Corner {'Latitude' if i % 2 == 0 else 'Longitude'} Point {i // 2 + 1}",
       "smap", 2, -0.075, 0.075)
    for i in range(8)
]  # fmt: skip
_FULL_CORNERS = [
    _t(82 + i, f"Corner {'Latitude' if i % 2 == 0 else 'Longitude'} Point {i // 2 + 1} (Full)",
       "smap", 4, -(90.0 if i % 2 == 0 else 180.0), 90.0 if i % 2 == 0 else 180.0)
    for i in range(8)
]  # fmt: skip

#: Every tag we interpret, by number. Others decode to ``bytes``.
TAGS: dict[int, Tag] = {
    t.tag: t
    for t in [
        _t(1, "Checksum", "uint", 2),
        _t(2, "Precision Time Stamp", "time", 8),
        _t(3, "Mission ID", "text", _MAX_TEXT),
        _t(4, "Platform Tail Number", "text", _MAX_TEXT),
        _t(5, "Platform Heading Angle", "umap", 2, 0.0, 360.0),
        _t(6, "Platform Pitch Angle", "smap", 2, -20.0, 20.0),
        _t(7, "Platform Roll Angle", "smap", 2, -50.0, 50.0),
        _t(8, "Platform True Airspeed", "uint", 1),
        _t(9, "Platform Indicated Airspeed", "uint", 1),
        _t(10, "Platform Designation", "text", _MAX_TEXT),
        _t(11, "Image Source Sensor", "text", _MAX_TEXT),
        _t(12, "Image Coordinate System", "text", _MAX_TEXT),
        _t(13, "Sensor Latitude", "smap", 4, -90.0, 90.0),
        _t(14, "Sensor Longitude", "smap", 4, -180.0, 180.0),
        _t(15, "Sensor True Altitude", "umap", 2, *_ALT),
        _t(16, "Sensor Horizontal Field of View", "umap", 2, 0.0, 180.0),
        _t(17, "Sensor Vertical Field of View", "umap", 2, 0.0, 180.0),
        _t(18, "Sensor Relative Azimuth Angle", "umap", 4, 0.0, 360.0),
        _t(19, "Sensor Relative Elevation Angle", "smap", 4, -180.0, 180.0),
        _t(20, "Sensor Relative Roll Angle", "umap", 4, 0.0, 360.0),
        _t(21, "Slant Range", "umap", 4, 0.0, 5_000_000.0),
        _t(22, "Target Width", "umap", 2, 0.0, 10_000.0),
        _t(23, "Frame Center Latitude", "smap", 4, -90.0, 90.0),
        _t(24, "Frame Center Longitude", "smap", 4, -180.0, 180.0),
        _t(25, "Frame Center Elevation", "umap", 2, *_ALT),
        *_CORNERS,
        _t(34, "Icing Detected", "uint", 1),
        _t(35, "Wind Direction", "umap", 2, 0.0, 360.0),
        _t(36, "Wind Speed", "umap", 1, 0.0, 100.0),
        _t(37, "Static Pressure", "umap", 2, 0.0, 5000.0),
        _t(38, "Density Altitude", "umap", 2, *_ALT),
        _t(39, "Outside Air Temperature", "int", 1),
        _t(40, "Target Location Latitude", "smap", 4, -90.0, 90.0),
        _t(41, "Target Location Longitude", "smap", 4, -180.0, 180.0),
        _t(42, "Target Location Elevation", "umap", 2, *_ALT),
        _t(43, "Target Track Gate Width", "umap", 1, 0.0, 510.0),
        _t(44, "Target Track Gate Height", "umap", 1, 0.0, 510.0),
        _t(45, "Target Error Estimate - CE90", "umap", 2, 0.0, 4095.0),
        _t(46, "Target Error Estimate - LE90", "umap", 2, 0.0, 4095.0),
        _t(47, "Generic Flag Data", "uint", 1),
        _t(48, "Security Local Set", "bytes"),
        _t(56, "Platform Ground Speed", "uint", 1),
        _t(57, "Ground Range", "umap", 4, 0.0, 5_000_000.0),
        _t(58, "Platform Fuel Remaining", "umap", 2, 0.0, 10_000.0),
        _t(59, "Platform Call Sign", "text", _MAX_TEXT),
        _t(64, "Platform Magnetic Heading", "umap", 2, 0.0, 360.0),
        _t(65, "UAS Datalink LS Version Number", "uint", 1),
        _t(72, "Event Start Time - UTC", "time", 8),
        _t(74, "VMTI Local Set", "bytes"),
        _t(75, "Sensor Ellipsoid Height", "umap", 2, *_ALT),
        _t(76, "Alternate Platform Ellipsoid Height", "umap", 2, *_ALT),
        _t(78, "Frame Center Height Above Ellipsoid", "umap", 2, *_ALT),
        *_FULL_CORNERS,
        _t(90, "Platform Pitch Angle (Full)", "smap", 4, -90.0, 90.0),
        _t(91, "Platform Roll Angle (Full)", "smap", 4, -90.0, 90.0),
        _t(96, "Target Width Extended", "imapb", 8, 0.0, 1_500_000.0, 3),
        _t(103, "Density Altitude Extended", "imapb", 8, *_ALT_EXT, 3),
        _t(104, "Sensor Ellipsoid Height Extended", "imapb", 8, *_ALT_EXT, 3),
        _t(105, "Alternate Platform Ellipsoid Height Extended", "imapb", 8, *_ALT_EXT, 3),
        _t(112, "Platform Course Angle", "imapb", 8, 0.0, 360.0, 2),
        _t(113, "Altitude Above Ground Level (AGL)", "imapb", 4, *_ALT_EXT, 3),
        _t(129, "Target ID", "text", 32),
        _t(136, "Leap Seconds", "int", 4),
        _t(137, "Correction Offset", "int", 8),
    ]
}


@lru_cache(maxsize=256)
def _imapb(low: float, high: float, length: int) -> Imapb:
    return Imapb(low, high, length)


def resolution(tag: int, length: int | None = None) -> float:
    """One LSB of ``tag``'s mapping in its units (at ``length`` bytes for IMAPB); 1 for integers."""
    t = TAGS[tag]
    if t.kind == "umap":
        return (t.high - t.low) / ((1 << (8 * t.length)) - 1)
    if t.kind == "smap":
        return t.high / ((1 << (8 * t.length - 1)) - 1)
    if t.kind == "imapb":
        return _imapb(t.low, t.high, length or t.default_length).resolution
    if t.kind == "time":
        return 1e-6
    return 1.0


# -- encoding ---------------------------------------------------------------------------------


def _encode_value(t: Tag, value: Value) -> bytes | None:
    """The bytes of one item's value, or None when it cannot be represented (left out)."""
    kind = t.kind
    if type(value) is float or type(value) is int:
        # The hot path: a plain number for a mapped tag (most of every packet).
        if kind == "smap":
            if not t.low <= value <= t.high:  # NaN fails too
                return _INDICATORS[t.length]
            return round(value * _SCALES[t.tag]).to_bytes(t.length, "big", signed=True)
        if kind == "umap":
            if not t.low <= value <= t.high:
                return None
            return round((value - t.low) * _SCALES[t.tag]).to_bytes(t.length, "big")
    if kind == "text":
        if not isinstance(value, str):
            raise TypeError(f"ST 0601 tag {t.tag}: expected str, got {type(value).__name__}")
        # ST 0107: text is trimmed of blanks and controls at both ends.
        text = value.strip(_TRIM).encode("ascii", "replace")[: t.length].strip(_TRIM.encode())
        return text or None  # a zero-length item means "unknown" to receivers: leave it out
    if kind == "bytes":
        if not isinstance(value, bytes):
            raise TypeError(f"ST 0601 tag {t.tag}: expected bytes, got {type(value).__name__}")
        return value
    if kind == "time":
        if not isinstance(value, datetime) or value.tzinfo is None:
            raise TypeError(f"ST 0601 tag {t.tag}: expected an aware datetime")
        micros = (value - _EPOCH) // timedelta(microseconds=1)
        return micros.to_bytes(8, "big") if 0 <= micros < 1 << 64 else None
    if isinstance(value, Special):
        # Only the signed mapped tags have an error indicator; the others leave it out.
        return _INDICATORS[t.length] if kind == "smap" else None
    if isinstance(value, str | bytes | datetime):
        raise TypeError(f"ST 0601 tag {t.tag}: expected a number, got {type(value).__name__}")
    if kind in ("smap", "umap"):
        return _encode_value(t, float(value))  # a bool or another int or float subclass
    if kind == "imapb":
        if not t.low <= value <= t.high:  # NaN fails too
            return None
        return _imapb(t.low, t.high, t.default_length).encode(value)
    # Integers ("uint", "int"): whole numbers that fit the tag's largest length.
    if isinstance(value, float) and not value.is_integer():
        raise TypeError(f"ST 0601 tag {t.tag}: expected an integer, got {value!r}")
    number = int(value)
    signed = kind == "int"
    bits = (number if number >= 0 else ~number).bit_length() + (1 if signed else 0)
    size = t.length if t.tag in _FIXED_INTEGERS else max(1, (bits + 7) // 8)
    if size > t.length or (number < 0 and not signed):
        return None
    try:
        return number.to_bytes(size, "big", signed=signed)
    except OverflowError:
        return None


def _scale(t: Tag) -> float:
    if t.kind == "smap":
        return ((1 << (8 * t.length - 1)) - 1) / t.high
    return ((1 << (8 * t.length)) - 1) / (t.high - t.low)


#: Raw units per unit of value, per mapped tag.
_SCALES: dict[int, float] = {t.tag: _scale(t) for t in TAGS.values() if t.kind in ("smap", "umap")}
#: The reserved error indicator (0x80 0x00 ...) by length.
_INDICATORS: dict[int, bytes] = {n: b"\x80" + bytes(n - 1) for n in (1, 2, 4, 8)}

#: Integer tags whose length is fixed (the rest are written in their shortest form).
_FIXED_INTEGERS = frozenset({1, 8, 9, 34, 39, 47, 56, 65})


#: Each interpreted tag's BER-OID bytes, encoded once.
_OIDS: dict[int, bytes] = {tag: encode_ber_oid(tag) for tag in TAGS}


def _item(tag: int, value: bytes) -> bytes:
    oid = _OIDS.get(tag) or encode_ber_oid(tag)
    n = len(value)
    return oid + (bytes((n,)) if n < 0x80 else encode_ber_length(n)) + value


def encode(values: Mapping[int, Value]) -> bytes:
    """One ST 0601 packet: tag 2 first, the rest in tag order, the checksum (tag 1) last.

    Tags not in ``TAGS`` take ``bytes`` and are written as given. Raises ``TypeError`` for
    a value of the wrong type for its tag (a bug in the caller); out-of-range values follow
    the module docstring's rules.
    """
    body = bytearray()
    order = sorted(values)
    if _TIME_TAG in values:
        order.remove(_TIME_TAG)
        order.insert(0, _TIME_TAG)
    for tag in order:
        if tag == _CHECKSUM_TAG:
            continue
        value = values[tag]
        t = TAGS.get(tag)
        if t is None:
            if not isinstance(value, bytes):
                raise TypeError(f"ST 0601 tag {tag} is not interpreted: expected bytes")
            encoded: bytes | None = value
        else:
            encoded = _encode_value(t, value)
        if encoded is not None:
            body += _item(tag, encoded)
    body += b"\x01\x02"
    head = UAS_LS_KEY + encode_ber_length(len(body) + 2)
    total = checksum(head + body)
    return bytes(head + body) + total.to_bytes(2, "big")


# -- decoding ---------------------------------------------------------------------------------


def _decode_value(t: Tag, data: memoryview) -> Value:
    kind, n = t.kind, len(data)
    if kind == "text":
        return bytes(data).decode("utf-8", "replace")
    if kind == "bytes":
        return bytes(data)
    if kind == "time":
        if n != 8:
            return bytes(data)
        micros = int.from_bytes(data, "big")
        # A datetime ends in year 9999: a larger stamp is kept as its bytes, not interpreted.
        return _EPOCH + timedelta(microseconds=micros) if micros < _MAX_MICROS else bytes(data)
    if kind == "imapb":
        if not 1 <= n <= t.length:
            return bytes(data)
        return _imapb(t.low, t.high, n).decode(data)
    if kind in ("uint", "int"):
        if not 1 <= n <= t.length:
            return bytes(data)
        return int.from_bytes(data, "big", signed=kind == "int")
    if n != t.length:
        return bytes(data)
    if kind == "smap":
        raw = int.from_bytes(data, "big", signed=True)
        bits = 8 * n - 1
        if raw == -(1 << bits):
            return Special.ERROR
        return raw * t.high / ((1 << bits) - 1)
    raw = int.from_bytes(data, "big")
    return t.low + raw * (t.high - t.low) / ((1 << (8 * n)) - 1)


def decode(packet: bytes, *, verify_checksum: bool = True) -> dict[int, Value]:
    """``{tag: value}`` of one ST 0601 packet (the first of a tag that appears twice).

    The checksum item is checked (when ``verify_checksum``) and left out of the result.
    Raises ``Malformed`` for another key, a length that does not match the packet, items that
    overrun the set, or a missing or wrong checksum.
    """
    if not packet.startswith(UAS_LS_KEY):
        raise Malformed("KLV: not an ST 0601 UAS Datalink Local Set key")
    length, value_at = decode_ber_length(packet, len(UAS_LS_KEY))
    if value_at + length != len(packet):
        raise Malformed(f"KLV: packet is {len(packet)} bytes, its length says {value_at + length}")
    out: dict[int, Value] = {}
    stored: int | None = None
    for tag, data in iter_items(memoryview(packet)[value_at:]):
        if tag == _CHECKSUM_TAG:
            if len(data) != 2:
                raise Malformed(f"KLV: checksum item of {len(data)} bytes")
            stored = int.from_bytes(data, "big")
            continue
        if tag in out:
            continue
        t = TAGS.get(tag)
        out[tag] = bytes(data) if t is None else _decode_value(t, data)
    if verify_checksum:
        if stored is None or not packet.endswith(b"\x01\x02" + packet[-2:]):
            raise Malformed("KLV: no checksum item at the end of the packet")
        computed = checksum(memoryview(packet)[:-2])
        if computed != stored:
            raise Malformed(f"KLV: checksum {stored:04x} stored, {computed:04x} computed")
    return out


def is_finite_number(value: Value) -> bool:
    """True for a real, finite number (not a ``Special``, text or time)."""
    return isinstance(value, int | float) and math.isfinite(value)
