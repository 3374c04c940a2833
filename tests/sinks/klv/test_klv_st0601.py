"""The ST 0601 codec: round trips within each tag's precision, framing, checksum, fuzzing."""

from __future__ import annotations

import contextlib
import math
from datetime import UTC, datetime
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from klv_values import packets

from gateway.errors import Malformed
from gateway.testing import fuzz_examples
from sinks.klv.ber import (
    UAS_LS_KEY,
    decode_ber_length,
    decode_ber_oid,
    encode_ber_length,
    encode_ber_oid,
    split_packets,
)
from sinks.klv.imapb import Imapb, Special
from sinks.klv.st0601 import TAGS, decode, encode, resolution

#: MISB ST 0902.5 "dynamic only" sample (the spec digest, §6 A).
ST0902_SAMPLE = bytes.fromhex(
    "060e2b34020b01010e0103010100000061020800046050584e0180050271c20602fd3d070208b80d045595b66d"
    "0e045b5360c40f02c2211002cd9c1102d9171204724a0a20130487f84b86140400000000150403830926160212"
    "811704f101a229180414bc082b190234f34101060102c850"
)


def spec_checksum(packet_without_value: bytes) -> int:
    """ST 0601's checksum as the spec words it, written apart from the codec's."""
    words = 0
    for index, byte in enumerate(packet_without_value):
        words += byte * 256 if index % 2 == 0 else byte
    return words % 65536


def assert_close(tag: int, sent: Any, got: Any) -> None:
    t = TAGS[tag]
    if t.kind in ("umap", "smap", "imapb"):
        assert isinstance(got, float), (tag, got)
        assert abs(got - sent) <= resolution(tag) * 1.0001 + 1e-9 * abs(sent), (tag, sent, got)
    elif t.kind == "text":
        assert got == sent[: t.length]
    else:
        assert got == sent, (tag, sent, got)


class TestBer:
    @pytest.mark.parametrize(
        ("length", "wire"), [(0, "00"), (127, "7f"), (128, "8180"), (210, "81d2"), (300, "82012c")]
    )
    def test_length_uses_the_shortest_form(self, length: int, wire: str) -> None:
        assert encode_ber_length(length).hex() == wire
        assert decode_ber_length(bytes.fromhex(wire), 0) == (length, len(wire) // 2)

    @pytest.mark.parametrize(
        ("tag", "wire"), [(1, "01"), (127, "7f"), (128, "8100"), (136, "8108"), (143, "810f")]
    )
    def test_oid_tags_take_two_bytes_from_128(self, tag: int, wire: str) -> None:
        assert encode_ber_oid(tag).hex() == wire
        assert decode_ber_oid(bytes.fromhex(wire), 0) == (tag, len(wire) // 2)

    @given(st.integers(0, 2**32 - 1))
    def test_length_round_trip(self, length: int) -> None:
        wire = encode_ber_length(length)
        assert decode_ber_length(wire, 0) == (length, len(wire))

    @given(st.integers(0, 2**28 - 1))
    def test_oid_round_trip(self, tag: int) -> None:
        wire = encode_ber_oid(tag)
        assert decode_ber_oid(wire, 0) == (tag, len(wire))


class TestSample:
    def test_st0902_sample_decodes_to_the_published_values(self) -> None:
        values = decode(ST0902_SAMPLE)
        assert values[2] == datetime(2009, 1, 12, 22, 8, 22, tzinfo=UTC)
        expected = {5: 159.9744, 6: -0.4315, 7: 3.4059, 13: 60.176823, 14: 128.426759,
                    15: 14190.72, 21: 68590.98, 22: 722.82, 23: -10.542389, 24: 29.157890,
                    25: 3216.04}  # fmt: skip
        for tag, value in expected.items():
            assert values[tag] == pytest.approx(value, abs=0.01), tag
        assert values[65] == 6

    def test_st0902_sample_checksum_agrees_with_the_spec_formula(self) -> None:
        assert spec_checksum(ST0902_SAMPLE[:-2]) == 0xC850

    def test_reencoding_the_sample_gives_the_same_bytes(self) -> None:
        assert encode(decode(ST0902_SAMPLE)) == ST0902_SAMPLE

    def test_a_flipped_byte_fails_the_checksum(self) -> None:
        bad = bytearray(ST0902_SAMPLE)
        bad[ST0902_SAMPLE.index(bytes.fromhex("0d045595")) + 3] ^= 0x01  # in tag 13
        with pytest.raises(Malformed, match="checksum"):
            decode(bytes(bad))
        assert decode(bytes(bad), verify_checksum=False)[13] != decode(ST0902_SAMPLE)[13]


class TestRoundTrip:
    @settings(max_examples=fuzz_examples(60))
    @given(packets())
    def test_every_value_comes_back_within_its_tag_precision(self, values: dict[int, Any]) -> None:
        packet = encode(values)
        assert spec_checksum(packet[:-2]) == int.from_bytes(packet[-2:], "big")
        got = decode(packet)
        assert set(got) == set(values)
        for tag, sent in values.items():
            assert_close(tag, sent, got[tag])

    @given(packets([2, 65]), st.lists(st.integers(0, 5), max_size=8))
    def test_a_stream_of_packets_splits_back(self, values: dict[int, Any], junk: list[int]) -> None:
        packet = encode(values)
        stream = bytes(junk) + packet + bytes(junk) + packet
        assert list(split_packets(stream)) == [packet, packet]

    def test_time_stamp_comes_first_and_checksum_last(self) -> None:
        packet = encode({65: 19, 13: 58.0, 2: datetime(2026, 1, 1, tzinfo=UTC)})
        assert packet[:16] == UAS_LS_KEY
        assert packet[17:19] == b"\x02\x08"
        assert packet[-4:-2] == b"\x01\x02"


class TestErrorIndicators:
    @pytest.mark.parametrize("tag", [6, 7, 13, 14, 19, 23, 24, 26, 40, 90])
    @pytest.mark.parametrize("value", [1e9, -1e9, math.nan, Special.ERROR])
    def test_signed_tags_send_the_reserved_value_out_of_range(self, tag: int, value: Any) -> None:
        packet = encode({tag: value})
        n = TAGS[tag].length
        assert packet[17 + 2 : 17 + 2 + n] == b"\x80" + bytes(n - 1)
        assert decode(packet)[tag] is Special.ERROR

    @pytest.mark.parametrize(
        ("tag", "value"), [(5, 361.0), (15, -1000.0), (21, math.nan), (56, 300)]
    )
    def test_unsigned_tags_without_indicator_are_left_out(self, tag: int, value: Any) -> None:
        assert tag not in decode(encode({tag: value, 65: 19}))

    @pytest.mark.parametrize("value", [-1000.0, 50_000.0, math.inf, math.nan])
    def test_imapb_tags_out_of_range_are_left_out(self, value: float) -> None:
        assert 113 not in decode(encode({113: value, 65: 19}))

    @pytest.mark.parametrize(
        ("first", "special"),
        [(0xE0, Special.BELOW_MINIMUM), (0xE1, Special.ABOVE_MAXIMUM),
         (0xC8, Special.POSITIVE_INFINITY), (0xD0, Special.NAN), (0xC1, Special.OTHER)],
    )  # fmt: skip
    def test_imapb_code_words_decode_as_special(self, first: int, special: Special) -> None:
        assert (
            decode(
                encode({113: 0.0, 65: 19}).replace(
                    b"\x71\x03" + Imapb(-900, 40_000, 3).encode(0.0),
                    b"\x71\x03" + bytes((first, 0, 0)),
                ),
                verify_checksum=False,
            )[113]
            is special
        )


class TestImapb:
    @given(
        st.floats(-1e6, 1e6, allow_nan=False),
        st.floats(1e-3, 1e7, allow_nan=False),
        st.integers(1, 8),
        st.floats(0, 1),
    )
    def test_round_trip_within_one_step(self, low: float, span: float, n: int, f: float) -> None:
        mapping = Imapb(low, low + span, n)
        x = low + f * span
        got = mapping.decode(mapping.encode(x))
        assert isinstance(got, float)
        assert abs(got - x) <= mapping.resolution * 1.0001 + 1e-9 * abs(x)

    def test_zero_is_exact_in_a_range_spanning_zero(self) -> None:
        mapping = Imapb(-900.0, 40_000.0, 3)
        assert mapping.decode(mapping.encode(0.0)) == 0.0


class TestFuzz:
    @settings(max_examples=fuzz_examples(500))
    @given(st.binary(max_size=300))
    def test_arbitrary_bytes_decode_or_raise_malformed(self, data: bytes) -> None:
        for packet in (data, UAS_LS_KEY + data):
            with contextlib.suppress(Malformed):
                decode(packet)
            with contextlib.suppress(Malformed):
                list(split_packets(packet))

    @settings(max_examples=fuzz_examples(100))
    @given(packets([2, 5, 13, 65, 96, 136]), st.data())
    def test_corrupted_packets_decode_or_raise_malformed(self, values: Any, data: Any) -> None:
        packet = bytearray(encode(values))
        index = data.draw(st.integers(0, len(packet) - 1))
        packet[index] = data.draw(st.integers(0, 255))
        with contextlib.suppress(Malformed):
            decode(bytes(packet), verify_checksum=data.draw(st.booleans()))
