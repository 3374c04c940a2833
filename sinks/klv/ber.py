"""SMPTE 336 KLV framing: BER lengths, BER-OID tags, the ST 0601 checksum, packet splitting.

Pure byte work with no knowledge of what a tag means (that is ``st0601``). Every reader
here takes bytes from outside: it is bounded by the buffer it is given and raises only
``Malformed``.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

from gateway.errors import Malformed

__all__ = [
    "MAX_BER_LENGTH_BYTES",
    "UAS_LS_KEY",
    "checksum",
    "decode_ber_length",
    "decode_ber_oid",
    "encode_ber_length",
    "encode_ber_oid",
    "iter_items",
    "split_packets",
]

#: The 16-byte Universal Label of the MISB ST 0601 UAS Datalink Local Set.
UAS_LS_KEY = bytes.fromhex("060e2b34020b01010e01030101000000")
#: A long-form BER length of more than this many bytes (4 GiB) is never a real packet.
MAX_BER_LENGTH_BYTES = 4
#: BER-OID tags longer than this (2^28) are not used by any MISB local set.
_MAX_OID_BYTES = 4


def encode_ber_length(length: int) -> bytes:
    """The shortest BER form of ``length``: one byte below 128, else ``0x80 | n`` + n bytes."""
    if length < 0:
        raise ValueError(f"BER length: expected >= 0, got {length}")
    if length < 0x80:
        return bytes((length,))
    body = length.to_bytes((length.bit_length() + 7) // 8, "big")
    return bytes((0x80 | len(body),)) + body


def decode_ber_length(data: bytes | memoryview, offset: int) -> tuple[int, int]:
    """(length, offset after it) of the BER length at ``offset``; ``Malformed`` if cut off."""
    if offset >= len(data):
        raise Malformed("KLV: BER length missing at the end of the buffer")
    first = data[offset]
    if first < 0x80:
        return first, offset + 1
    count = first & 0x7F
    if count == 0 or count > MAX_BER_LENGTH_BYTES:
        raise Malformed(f"KLV: BER length of {count} bytes is not supported")
    end = offset + 1 + count
    if end > len(data):
        raise Malformed("KLV: BER length cut off")
    return int.from_bytes(data[offset + 1 : end], "big"), end


def encode_ber_oid(tag: int) -> bytes:
    """A tag as BER-OID: 7 bits a byte, big-endian, the high bit set on all but the last."""
    if tag < 0:
        raise ValueError(f"BER-OID tag: expected >= 0, got {tag}")
    out = [tag & 0x7F]
    tag >>= 7
    while tag:
        out.append(0x80 | (tag & 0x7F))
        tag >>= 7
    return bytes(reversed(out))


def decode_ber_oid(data: bytes | memoryview, offset: int) -> tuple[int, int]:
    """(tag, offset after it) of the BER-OID at ``offset``; ``Malformed`` if cut off or huge."""
    tag = 0
    for i in range(_MAX_OID_BYTES):
        if offset + i >= len(data):
            raise Malformed("KLV: tag cut off")
        byte = data[offset + i]
        tag = (tag << 7) | (byte & 0x7F)
        if not byte & 0x80:
            return tag, offset + i + 1
    raise Malformed(f"KLV: tag longer than {_MAX_OID_BYTES} bytes")


def checksum(data: bytes | memoryview) -> int:
    """The ST 0601 16-bit running sum of big-endian words over ``data`` (low 16 bits).

    ``data`` is the packet up to and including the checksum item's length byte; an odd
    trailing byte counts as the high byte of a word.
    """
    view = bytes(data)
    words = len(view) // 2
    total = int(sum(struct.unpack_from(f">{words}H", view)))
    if len(view) & 1:
        total += view[-1] << 8
    return total & 0xFFFF


def iter_items(value: bytes | memoryview) -> Iterator[tuple[int, memoryview]]:
    """(tag, value) of every item of a local set's value, in order; ``Malformed`` if cut off."""
    view = memoryview(value)
    offset = 0
    while offset < len(view):
        tag, offset = decode_ber_oid(view, offset)
        length, offset = decode_ber_length(view, offset)
        end = offset + length
        if end > len(view):
            raise Malformed(f"KLV: item {tag} claims {length} bytes, {len(view) - offset} left")
        yield tag, view[offset:end]
        offset = end


def split_packets(
    data: bytes, key: bytes = UAS_LS_KEY, *, max_packet_bytes: int = 65_536
) -> Iterator[bytes]:
    """Each whole KLV packet with ``key`` in a byte stream (a ``.bin`` capture, a datagram).

    Bytes before a key, and packets with another key, are skipped; a packet cut off at the
    end, or longer than ``max_packet_bytes``, ends the iteration with ``Malformed``.
    """
    offset = 0
    while True:
        start = data.find(key, offset)
        if start < 0:
            return
        length, value_at = decode_ber_length(data, start + len(key))
        end = value_at + length
        if length > max_packet_bytes:
            raise Malformed(f"KLV: packet of {length} bytes, more than {max_packet_bytes}")
        if end > len(data):
            raise Malformed(f"KLV: packet at byte {start} cut off ({end - len(data)} missing)")
        yield data[start:end]
        offset = end
