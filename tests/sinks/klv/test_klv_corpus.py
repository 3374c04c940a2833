"""Our ST 0601 decoder on real recorded KLV (the shared corpus), against its MANIFEST."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
from datetime import UTC, datetime
from functools import cache, partial
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from tools import need

from gateway.errors import Malformed
from gateway.testing import fuzz_examples
from sinks.klv.ber import split_packets
from sinks.klv.imapb import Special
from sinks.klv.st0601 import decode

pytestmark = pytest.mark.corpus


def klv_file(name: str) -> bytes:
    """A file under ``shared/corpus/klv`` (any subfolder), or skip when the corpus is absent."""
    root = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
    for corpus in (root.parent / "shared" / "corpus",):
        found = sorted((corpus / "klv").rglob(name)) if (corpus / "klv").is_dir() else []
        if found:
            return found[0].read_bytes()
    pytest.skip(f"corpus file absent: klv/**/{name}")


def test_cheyenne_every_packet_decodes_with_a_good_checksum() -> None:
    packets = [decode(p) for p in split_packets(klv_file("Cheyenne.bin"))]
    assert len(packets) == 407
    first = packets[0]
    assert first[2] == datetime(2012, 9, 19, 20, 40, 44, 105300, tzinfo=UTC)
    assert (first[3], first[4], first[10]) == ("ESRI_Metadata_Collect", "N97826", "C208B")
    expected = {5: 201.2726, 13: 41.1438457, 14: -104.8055968, 15: 2936.37,
                23: 41.1383084, 24: -104.7855039, 25: 1855.36}  # fmt: skip
    for tag, value in expected.items():
        assert first[tag] == pytest.approx(value, abs=0.01 if tag in (5, 15, 25) else 1e-6), tag
    assert first[65] == 1
    assert isinstance(first[48], bytes)  # the nested security set, kept whole


def test_realflight_error_indicators_and_values() -> None:
    packets = [decode(p) for p in split_packets(klv_file("realflight.bin"))]
    assert len(packets) == 19
    first = packets[0]
    assert first[2] == datetime(2019, 9, 12, 14, 7, 1, 29439, tzinfo=UTC)
    assert first[3] == "mission12/09/2019 14:07:01"
    assert (first[10], first[11]) == ("AR5", "Sony FCB-EV7500")
    assert first[13] == pytest.approx(39.3483892, abs=1e-6)
    assert first[14] == pytest.approx(-9.3207055, abs=1e-6)
    assert first[5] == pytest.approx(104.399, abs=0.001)
    assert first[65] == 11
    # 0x80000000, ST 0601's "out of range" indicator, which klvdata 0.0.3 raises on.
    for tag in (19, 23, 24, 82, 83, 84, 85):
        assert first[tag] is Special.ERROR, tag
    assert b"//PT" in first[48]  # type: ignore[operator]


def test_st0902_dynamic_constant_original_is_good_and_the_patched_one_is_not() -> None:
    good = decode(klv_file("DynamicConstantMISMMSPacketData_0ed97ca_original.bin"))
    assert (good[3], good[10], good[11]) == ("Mission 12", "Predator", "EO Nose")
    assert good[20] == 0.0
    with pytest.raises(Malformed, match="checksum"):
        decode(klv_file("DynamicConstantMISMMSPacketData.bin"))


def test_kwiver_h264_klv_ts_all_tags_including_two_byte_ones(tmp_path: Path) -> None:
    """The ST 0601 example packets in an MPEG-TS (tags 1-142), extracted with ffmpeg."""
    need("ffmpeg")
    ffmpeg = shutil.which("ffmpeg") or "ffmpeg"
    source = tmp_path / "h264_klv.ts"
    source.write_bytes(klv_file("h264_klv.ts"))
    out = tmp_path / "klv.bin"
    subprocess.run(
        [ffmpeg, "-v", "error", "-y", "-i", str(source), "-map", "0:d:0", "-c", "copy",
         "-f", "data", str(out)],
        check=True, timeout=60,
    )  # fmt: skip
    packets = [decode(p) for p in split_packets(out.read_bytes())]
    assert len(packets) == 30
    first = packets[0]
    assert first[2] == datetime(2008, 10, 24, 0, 13, 29, 913000, tzinfo=UTC)
    assert (first[3], first[4], first[10], first[11]) == ("MISSION01", "AF-101", "MQ1-B", "EO")
    assert first[13] == pytest.approx(60.1768230, abs=1e-6)
    assert first[14] == pytest.approx(128.4267590, abs=1e-6)
    assert first[65] == 17
    assert set(range(128, 143)) <= set(first)  # BER-OID two-byte tags, read by their length
    assert first[113] == pytest.approx(2150.0, abs=0.01)  # IMAPB


@cache
def corpus_seeds() -> list[bytes]:
    """Real packets to mutate: Cheyenne, realflight and the ST 0902 samples."""
    names = ("Cheyenne.bin", "realflight.bin", "DynamicOnlyMISMMSPacketData.bin",
             "DynamicConstantMISMMSPacketData_0ed97ca_original.bin")  # fmt: skip
    return [p for name in names for p in list(split_packets(klv_file(name)))[:25]]


def with_checksum(packet: bytearray) -> bytes:
    """``packet`` with its last two bytes set to the running sum of the rest (spec §2)."""
    total = sum((b << 8) if i % 2 == 0 else b for i, b in enumerate(packet[:-2]))
    packet[-2:] = (total & 0xFFFF).to_bytes(2, "big")
    return bytes(packet)


mutation = st.tuples(st.integers(0, 1 << 16), st.integers(0, 255), st.sampled_from("sidt"))


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(st.data(), st.lists(mutation, min_size=1, max_size=6), st.booleans())
def test_mutated_corpus_packets_decode_or_raise_malformed(
    data: st.DataObject, mutations: list[tuple[int, int, str]], fix_checksum: bool
) -> None:
    """Real packets with bytes set, inserted, deleted or cut off; with the checksum made good
    again half the time, so the mutation reaches the item parser behind it."""
    packet = bytearray(data.draw(st.sampled_from(corpus_seeds())))
    for position, byte, op in mutations:
        i = position % (len(packet) + 1)
        if op == "s" and i < len(packet):
            packet[i] = byte
        elif op == "i":
            packet[i:i] = bytes([byte])
        elif op == "d":
            del packet[i : i + 1 + byte % 8]
        elif op == "t":
            del packet[i:]
    wire = with_checksum(packet) if fix_checksum and len(packet) >= 2 else bytes(packet)
    unchecked = partial(decode, verify_checksum=False)
    for decoder in (decode, unchecked, lambda b: list(split_packets(b))):
        with contextlib.suppress(Malformed):  # and nothing else
            decoder(wire)
