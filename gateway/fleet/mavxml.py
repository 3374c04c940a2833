"""MAVLink message definitions read from dialect XML: wire order, struct format and CRC_EXTRA.

The XML that pymavlink carries (``pymavlink/dialects/v20/*.xml``) and the project's own
``gateway/fleet/fischer_dialect.xml`` are the source of truth for how a message is laid out
on the wire; ``read_dialect`` turns one dialect file and everything it includes into
``MessageDef`` records, computed the way the MAVLink specification defines them:

- the wire order puts the base fields first, stably sorted by the size of their element type
  (8, 4, 2, then 1 byte), then the extension fields (after ``<extensions/>``) as declared;
- CRC_EXTRA is the X.25 checksum (CRC-16/MCRF4XX) of the message name and of each base
  field's type, name and array length in wire order, folded to one byte;
- the payload is little-endian and packed; a MAVLink 2 sender may drop trailing zero bytes
  (the receiver fills them back in), and the extensions are never part of CRC_EXTRA.

Nothing here is hand-typed per message: ``gateway.fleet.fastdecode`` builds its decoders
from these records. A file that breaks these rules raises ``ValueError`` naming the file,
the message and the field.
"""

from __future__ import annotations

import binascii
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from xml.etree.ElementTree import Element

from defusedxml import DefusedXmlException, ElementTree

__all__ = [
    "FieldDef",
    "MessageDef",
    "pymavlink_xml_dir",
    "read_dialect",
    "x25_crc",
]

#: Element size in bytes and ``struct`` code of each MAVLink type.
_TYPES: dict[str, tuple[int, str]] = {
    "uint64_t": (8, "Q"),
    "int64_t": (8, "q"),
    "double": (8, "d"),
    "uint32_t": (4, "I"),
    "int32_t": (4, "i"),
    "float": (4, "f"),
    "uint16_t": (2, "H"),
    "int16_t": (2, "h"),
    "uint8_t": (1, "B"),
    "int8_t": (1, "b"),
    "char": (1, "c"),
}
#: The largest payload a MAVLink frame can carry (its length is one byte).
MAX_PAYLOAD = 255
#: Bit-reversal of every byte value: CRC-16/MCRF4XX is the reflected form of CRC-CCITT.
_REVERSED = bytes(int(f"{value:08b}"[::-1], 2) for value in range(256))


def x25_crc(data: bytes, crc: int = 0xFFFF) -> int:
    """The MAVLink checksum (CRC-16/MCRF4XX, "X.25") of ``data``, continuing from ``crc``.

    The standard library's ``binascii.crc_hqx`` computes the same polynomial without
    reflection, so it runs on bit-reversed bytes from a bit-reversed start.
    """
    start = (_REVERSED[crc & 0xFF] << 8) | _REVERSED[crc >> 8]
    value = binascii.crc_hqx(data.translate(_REVERSED), start)
    return (_REVERSED[value & 0xFF] << 8) | _REVERSED[value >> 8]


@dataclass(frozen=True, slots=True)
class FieldDef:
    """One field of a message: its name, element type, array length (0: a scalar)."""

    name: str
    type: str
    array_length: int
    is_extension: bool

    @property
    def element_size(self) -> int:
        """Bytes per element."""
        return _TYPES[self.type][0]

    @property
    def wire_length(self) -> int:
        """Bytes the field takes in the payload."""
        return self.element_size * max(self.array_length, 1)

    @property
    def struct_code(self) -> str:
        """Its ``struct`` format: a char array is one bytes value, other arrays N values."""
        code = _TYPES[self.type][1]
        if not self.array_length:
            return code
        return f"{self.array_length}{'s' if code == 'c' else code}"


@dataclass(frozen=True, slots=True)
class MessageDef:
    """One message as the wire carries it."""

    msgid: int
    name: str
    fields: tuple[FieldDef, ...]
    """In declaration order (the order pymavlink's ``fieldnames`` lists)."""
    wire_fields: tuple[FieldDef, ...]
    """In wire order: base fields by descending element size, then the extensions."""
    crc_extra: int
    source: str
    """The XML file that defines it."""

    @property
    def struct_format(self) -> str:
        """``struct`` format of the whole payload, extensions included."""
        return "<" + "".join(f.struct_code for f in self.wire_fields)

    @property
    def base_length(self) -> int:
        """Payload bytes without the extensions (what a MAVLink 1 sender sends)."""
        return sum(f.wire_length for f in self.wire_fields if not f.is_extension)

    @property
    def length(self) -> int:
        """Payload bytes with every extension."""
        return sum(f.wire_length for f in self.wire_fields)


def pymavlink_xml_dir() -> Path:
    """The directory of the installed pymavlink's MAVLink 2 dialect XML files."""
    import pymavlink

    root = Path(pymavlink.__file__).resolve().parent
    for candidate in (root / "dialects" / "v20", root / "message_definitions" / "v1.0"):
        if (candidate / "common.xml").is_file():
            return candidate
    raise ValueError(f"no MAVLink dialect XML (common.xml) in the pymavlink package at {root}")


def _field(element: Element, where: str, *, is_extension: bool) -> FieldDef:
    name = element.get("name") or ""
    declared = element.get("type") or ""
    if not name.isidentifier() or name.startswith("_"):
        raise ValueError(f"{where}: field name {name!r} is not a plain identifier")
    base, bracket, rest = declared.partition("[")
    length = 0
    if bracket:
        if not rest.endswith("]") or not rest[:-1].isdigit():
            raise ValueError(f"{where}.{name}: bad array type {declared!r}")
        length = int(rest[:-1])
        if not 1 <= length <= MAX_PAYLOAD:
            raise ValueError(f"{where}.{name}: array length {length} out of 1..{MAX_PAYLOAD}")
    # The spec's aliases: the HEARTBEAT version byte, "array" for int8_t, types without "_t".
    if base == "uint8_t_mavlink_version":
        base = "uint8_t"
    elif base == "array":
        base = "int8_t"
    elif base not in _TYPES and base + "_t" in _TYPES:
        base += "_t"
    if base not in _TYPES:
        raise ValueError(f"{where}.{name}: unknown type {declared!r}")
    return FieldDef(name, base, length, is_extension)


def _crc_extra(name: str, base_fields: Iterable[FieldDef]) -> int:
    crc = x25_crc(name.encode("ascii") + b" ")
    for f in base_fields:
        crc = x25_crc(f"{f.type} {f.name} ".encode("ascii"), crc)
        if f.array_length:
            crc = x25_crc(bytes([f.array_length]), crc)
    return (crc & 0xFF) ^ (crc >> 8)


def _message(element: Element, source: str) -> MessageDef:
    name = element.get("name") or ""
    where = f"{source}: message {name or '?'}"
    try:
        msgid = int(element.get("id") or "")
    except ValueError:
        raise ValueError(f"{where}: bad id {element.get('id')!r}") from None
    if not 0 <= msgid < 1 << 24 or not name.isidentifier():
        raise ValueError(f"{where}: bad id {msgid} or name")
    fields: list[FieldDef] = []
    in_extensions = False
    for child in element:
        if child.tag == "extensions":
            in_extensions = True
        elif child.tag == "field":
            fields.append(_field(child, where, is_extension=in_extensions))
    if not fields or len({f.name for f in fields}) != len(fields):
        raise ValueError(f"{where}: no fields, or two fields of one name")
    base = [f for f in fields if not f.is_extension]
    # sorted() is stable: fields of one size keep their declared order.
    wire = sorted(base, key=lambda f: f.element_size, reverse=True)
    wire += [f for f in fields if f.is_extension]
    message = MessageDef(
        msgid, name, tuple(fields), tuple(wire), _crc_extra(name, wire[: len(base)]), source
    )
    if message.length > MAX_PAYLOAD:
        raise ValueError(f"{where}: {message.length} payload bytes, more than {MAX_PAYLOAD}")
    return message


def _read(
    path: Path, search: tuple[Path, ...], seen: set[Path], out: dict[int, MessageDef]
) -> None:
    path = path.resolve()
    if path in seen:
        return
    seen.add(path)
    try:
        root = ElementTree.fromstring(path.read_bytes())
    except (OSError, ElementTree.ParseError, DefusedXmlException) as exc:
        raise ValueError(f"{path}: cannot read MAVLink XML: {exc}") from exc
    if root.tag != "mavlink":
        raise ValueError(f"{path}: not MAVLink XML (root element {root.tag!r})")
    for include in root.findall("include"):
        name = (include.text or "").strip()
        found = next((d / name for d in (path.parent, *search) if (d / name).is_file()), None)
        if found is None:
            raise ValueError(f"{path}: included {name!r} not found")
        _read(found, search, seen, out)
    for element in root.findall("messages/message"):
        message = _message(element, path.name)
        known = out.get(message.msgid)
        if known is not None and (known.name, known.fields) != (message.name, message.fields):
            raise ValueError(
                f"{path.name}: message id {message.msgid} ({message.name}) is also "
                f"{known.name} in {known.source}"
            )
        out[message.msgid] = message


def read_dialect(path: Path, search: Iterable[Path] = ()) -> dict[int, MessageDef]:
    """Every message of the dialect XML at ``path`` and of the files it includes, by id.

    An ``<include>`` is looked up beside the including file, then in ``search`` (for the
    project dialect: pymavlink's directory, which holds common.xml).
    """
    out: dict[int, MessageDef] = {}
    _read(Path(path), tuple(Path(d) for d in search), set(), out)
    names = [m.name for m in out.values()]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: two messages share a name")
    return out
