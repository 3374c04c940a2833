"""TAK protocol v1 wire format: protobuf fields, mesh and stream framing, both directions.

Written by hand (the ``TakMessage`` schema is a handful of proto3 fields; field numbers from
ATAK-CIV's ``commoncommo/core/impl/protobuf/*.proto``), so the tests' decoder, takproto, stays
independent of ours. The reader is bounded by its input and raises ``ProtoError`` for anything
that is not well-formed protobuf; it never allocates more than the input's size.
"""

from __future__ import annotations

import struct

__all__ = [
    "MESH_HEADER",
    "FieldValue",
    "Fields",
    "ProtoError",
    "double",
    "fixed64_double",
    "mesh_frame",
    "mesh_payload",
    "message",
    "read_fields",
    "read_varint",
    "stream_frame",
    "string",
    "uint",
    "varint",
]

#: Mesh (UDP) framing: magic 0xBF, protocol version 1 as a varint, magic 0xBF.
MESH_HEADER = b"\xbf\x01\xbf"
_MAGIC = 0xBF
_MAX_VARINT_BYTES = 10

FieldValue = int | bytes
Fields = dict[int, list[FieldValue]]


class ProtoError(ValueError):
    """Raised for bytes that are not well-formed protobuf or TAK framing; names the problem."""


# -- writing -------------------------------------------------------------------------------


def varint(value: int) -> bytes:
    """``value`` (≥ 0) as a protobuf base-128 varint."""
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _key(field: int, wire: int) -> bytes:
    return varint(field << 3 | wire)


def string(field: int, value: str | None) -> bytes:
    """A string field; empty or None is proto3's default and is left out."""
    if not value:
        return b""
    data = value.encode("utf-8")
    return _key(field, 2) + varint(len(data)) + data


def message(field: int, payload: bytes) -> bytes:
    """An embedded message field (written even when empty, so its presence is kept)."""
    return _key(field, 2) + varint(len(payload)) + payload


def uint(field: int, value: int) -> bytes:
    """An unsigned varint field (uint32/uint64); zero is the default and is left out."""
    return _key(field, 0) + varint(value) if value else b""


def double(field: int, value: float) -> bytes:
    """A double field; 0.0 is the default and is left out."""
    return _key(field, 1) + struct.pack("<d", value) if value != 0.0 else b""


def mesh_frame(payload: bytes) -> bytes:
    """TAK protocol v1 mesh (UDP) framing: ``bf 01 bf`` then the ``TakMessage``."""
    return MESH_HEADER + payload


def stream_frame(payload: bytes) -> bytes:
    """TAK protocol v1 stream (TCP/TLS) framing: ``bf``, varint length, ``TakMessage``."""
    return bytes((_MAGIC,)) + varint(len(payload)) + payload


# -- reading -------------------------------------------------------------------------------


def read_varint(data: bytes, pos: int) -> tuple[int, int]:
    """The varint at ``pos`` and the position after it; ``ProtoError`` if cut or too long."""
    value = shift = 0
    for index in range(pos, min(len(data), pos + _MAX_VARINT_BYTES)):
        byte = data[index]
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, index + 1
        shift += 7
    raise ProtoError("varint is truncated or longer than 10 bytes")


def read_fields(data: bytes) -> Fields:
    """Every field of one protobuf message: number → values (varints as int, else bytes).

    Fixed-width fields come back as their raw 8 or 4 bytes; embedded messages and strings as
    their bytes, to be read with this function or decoded by the caller.
    """
    fields: Fields = {}
    pos, end = 0, len(data)
    while pos < end:
        key, pos = read_varint(data, pos)
        number, wire = key >> 3, key & 0x7
        if number == 0:
            raise ProtoError("field number 0")
        value: FieldValue
        if wire == 0:
            value, pos = read_varint(data, pos)
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            if pos + size > end:
                raise ProtoError(f"field {number} is truncated")
            value, pos = data[pos : pos + size], pos + size
        elif wire == 2:
            length, pos = read_varint(data, pos)
            if pos + length > end:
                raise ProtoError(f"field {number} claims {length} bytes, {end - pos} remain")
            value, pos = data[pos : pos + length], pos + length
        else:
            raise ProtoError(f"field {number} has unsupported wire type {wire}")
        fields.setdefault(number, []).append(value)
    return fields


def fixed64_double(value: FieldValue, name: str) -> float:
    """A double read by ``read_fields``; ``ProtoError`` naming ``name`` if it is not one."""
    if not isinstance(value, bytes) or len(value) != 8:
        raise ProtoError(f"{name} is not a double")
    result: float = struct.unpack("<d", value)[0]
    return result


def mesh_payload(data: bytes) -> bytes:
    """The ``TakMessage`` inside a mesh datagram, or inside one stream frame.

    Mesh: ``bf 01 bf`` + message. Stream: ``bf`` + varint length + message, where the length
    must cover the rest of ``data`` exactly (one frame).
    """
    if data.startswith(MESH_HEADER):
        return data[len(MESH_HEADER) :]
    if not data or data[0] != _MAGIC:
        raise ProtoError("no TAK protocol magic byte 0xbf")
    length, pos = read_varint(data, 1)
    if pos + length != len(data):
        raise ProtoError(f"stream frame claims {length} bytes, {len(data) - pos} follow")
    return data[pos:]
