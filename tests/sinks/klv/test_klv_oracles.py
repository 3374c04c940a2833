"""Our ST 0601 packets read by independent decoders: stanag4609 (strict, checksum) and klvdata.

``stanag4609`` 0.4.0 verifies the checksum and knows ST 0601.19 (IMAPB, two-byte tags);
``klvdata`` 0.0.3 knows one-byte legacy tags only and raises on error indicators (both are
known limits, the spec digest §7), so it is asked only about the packets it can read.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from klv_values import packets

from gateway.testing import fuzz_examples
from sinks.klv.imapb import Special
from sinks.klv.st0601 import TAGS, Value, decode, encode, resolution

stanag = pytest.importorskip("stanag4609.st0601")
klvdata = pytest.importorskip("klvdata")

#: Tags both we and stanag4609 interpret the same way (numbers, text, time).
STANAG_TAGS = [2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22,
               23, 24, 25, *range(26, 34), 40, 41, 42, 45, 46, 56, 57, 58, 59, 65, 72, 75,
               78, 90, 91, 96, 103, 104, 105, 112, 113, 136, 137]  # fmt: skip
#: Tags klvdata 0.0.3 decodes correctly (not 39: read unsigned; not IMAPB; not >= 128).
KLVDATA_TAGS = [2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22,
                23, 24, 25, *range(26, 34), 40, 41, 42, 56, 57, 59, 65, 72, 75, 90, 91]  # fmt: skip
T0 = datetime(2026, 11, 22, 10, 15, 30, 250000, tzinfo=UTC)


def spec_checksum(packet: bytes) -> int:
    """The 16-bit running sum (spec digest §2), written apart from the codec."""
    total = 0
    for i, byte in enumerate(packet[:-2]):
        total += (byte << 8) if i % 2 == 0 else byte
    return total & 0xFFFF


def same(tag: int, ours: Value, theirs: Any) -> bool:
    if isinstance(ours, Special):  # we send only the legacy indicator
        indicators = {"out_of_range", "off_earth", "error", "reserved"}
        return ours is Special.ERROR and getattr(theirs, "value", None) in indicators
    if isinstance(ours, float):
        return abs(float(theirs) - ours) <= resolution(tag, 8) + 1e-9 * abs(ours)
    return bool(ours == theirs)


def check_stanag(packet: bytes) -> None:
    ours = decode(packet)
    theirs = {f.definition.tag: f.value for f in stanag.decode_uas_local_set(packet).fields}
    assert theirs.pop(1) == spec_checksum(packet) == int.from_bytes(packet[-2:], "big")
    assert set(theirs) == set(ours)
    for tag, value in ours.items():
        assert same(tag, value, theirs[tag]), (tag, value, theirs[tag])


def check_klvdata(packet: bytes) -> None:
    ours = decode(packet)
    (parsed,) = list(klvdata.StreamParser(packet))
    theirs = {key[0]: element.value for key, element in parsed.items.items()}
    assert set(theirs) - {1} == set(ours)
    for tag, value in ours.items():
        got = getattr(theirs[tag], "value", theirs[tag])
        if TAGS[tag].kind == "time":
            assert got.replace(tzinfo=UTC) == value
        elif isinstance(value, float):
            assert abs(float(got) - value) <= resolution(tag) + 1e-9 * abs(value), tag
        elif isinstance(value, int):
            assert float(got) == value, tag
        else:
            assert got == value, tag


required = st.fixed_dictionaries({2: st.just(T0), 65: st.just(19)})


@settings(max_examples=fuzz_examples(80))
@given(required, packets(STANAG_TAGS))
def test_stanag4609_reads_what_we_write(head: dict[int, Any], values: dict[int, Any]) -> None:
    check_stanag(encode(values | head))


@settings(max_examples=fuzz_examples(80))
@given(required, packets(KLVDATA_TAGS))
def test_klvdata_reads_what_we_write(head: dict[int, Any], values: dict[int, Any]) -> None:
    check_klvdata(encode(values | head))


@pytest.mark.parametrize("tag", [6, 13, 19, 23, 24, 90])
def test_stanag4609_reads_our_error_indicators(tag: int) -> None:
    packet = encode({2: T0, 65: 19, tag: float("nan")})
    check_stanag(packet)
    assert decode(packet)[tag] is Special.ERROR
