"""A decode fast path for the MAVLink messages the gateway handles, built from the dialect XML.

pymavlink's generic decode builds a header object, reorders fields in a Python loop and
calls a generated ``__init__`` per frame. For the messages the gateway acts on
(``GATEWAY_MESSAGES``: telemetry, detections, acknowledgements, mission and camera
messages) this module decodes a frame with one CRC call and one ``struct`` unpack into a
``FastMessage``: a tuple of the payload values in wire order plus the frame, whose fields
are read by name exactly as on pymavlink's message (same names, same values, arrays as
lists, enums as ints). Char fields follow pymavlink 2.4.50's classes: ``str`` cut at the
first NUL, ASCII with undecodable bytes replaced; in the project's own messages
(``gateway.fleet.dialect``, ``hopdialect``) they are ``bytes`` without trailing NULs.
The layout of every message (wire order, ``struct`` format, CRC_EXTRA, extensions,
MAVLink 2 zero truncation) comes from the XML that the installed pymavlink carries and
from ``fischer_dialect.xml`` (``gateway.fleet.mavxml``), read once per process.

It takes pymavlink's acceptance rules, frame by frame: MAVLink 1 (0xFE) and 2 (0xFD)
frames, the CRC over header and payload with the message's CRC_EXTRA, incompatibility
flags other than "signed" refused, a signed frame's 13 signature bytes outside the CRC and
not verified here (``gateway.fleet.security.signing`` does that, as today), a short
payload zero-filled and a long one cut to the message's length. It was checked against
pymavlink ``PYMAVLINK_CHECKED`` (tests/gateway/fleet/test_fastdecode.py: generated frames of
every message and the shared corpus). With any other pymavlink installed, with
``MAV_IGNORE_CRC`` set or when the XML cannot be read, ``default_decoder()`` is empty:
every frame falls back to pymavlink.

How a caller uses it (one datagram, tunnel payload or tlog record holds whole frames)::

    decoder = default_decoder()
    for frame in split_frames(data):          # gateway.fleet.mavlink; Malformed: use pymavlink
        try:
            msg = decoder.decode(frame)
        except Malformed:
            ...                               # count it as a bad frame, as pymavlink's BAD_DATA
            continue
        if msg is None:
            msg = <pymavlink, as today>       # not one of ours: unknown id, other message
        ...                                   # msg.get_type(), msg.get_srcSystem(), msg.lat ...

A ``FastMessage`` answers ``get_type``, ``get_msgId``, ``get_srcSystem``,
``get_srcComponent``, ``get_seq``, ``get_msgbuf`` (the frame as given) and every field
by name; it is immutable. A byte stream (TCP, serial) still needs pymavlink's
stateful parser to find frame boundaries.
"""

from __future__ import annotations

import os
import struct
from binascii import crc_hqx
from collections.abc import Callable, Collection, Iterable
from functools import cache
from importlib import metadata
from operator import itemgetter
from pathlib import Path
from typing import Any, ClassVar, cast

import structlog

from gateway.errors import Malformed
from gateway.fleet.mavxml import MessageDef, pymavlink_xml_dir, read_dialect

__all__ = [
    "GATEWAY_MESSAGES",
    "PYMAVLINK_CHECKED",
    "FastDecoder",
    "FastMessage",
    "default_decoder",
    "load_messages",
    "message_class",
]

log = structlog.get_logger(__name__)

#: The pymavlink release whose decode this module was checked against, field for field.
PYMAVLINK_CHECKED = "2.4.50"

#: The messages that have a handler in the gateway (normalise, ingest, session, commander,
#: video, hop schedules) and the project dialect's; tests keep this equal to the handlers.
GATEWAY_MESSAGES = frozenset(
    {
        "HEARTBEAT",
        "SYS_STATUS",
        "GLOBAL_POSITION_INT",
        "GPS_RAW_INT",
        "ATTITUDE",
        "VFR_HUD",
        "BATTERY_STATUS",
        "COMMAND_ACK",
        "CAMERA_FOV_STATUS",
        "GIMBAL_DEVICE_ATTITUDE_STATUS",
        "HOME_POSITION",
        "MISSION_ACK",
        "MISSION_COUNT",
        "MISSION_ITEM_INT",
        "MISSION_CURRENT",
        "MISSION_ITEM_REACHED",
        "MISSION_REQUEST",
        "MISSION_REQUEST_INT",
        "FISCHER_DETECTION",
        "FISCHER_DETECTION_ACK",
        "FISCHER_HOP_EVENT",
        "FISCHER_HOP_SCHEDULE",
        "FISCHER_HOP_SCHEDULE_ACK",
    }
)

_PROJECT_DIALECT = Path(__file__).resolve().parent / "fischer_dialect.xml"
_STX_V2 = 0xFD
#: Bit-reversal of every byte value. binascii.crc_hqx is CRC-CCITT; MAVLink's X.25 checksum
#: (CRC-16/MCRF4XX) is the same polynomial reflected, so the frame is checked bit-reversed.
_REVERSED = bytes(int(f"{value:08b}"[::-1], 2) for value in range(256))
#: crc_hqx's one-byte step, for appending CRC_EXTRA without building a new buffer.
_CCITT = [crc_hqx(bytes([value]), 0) for value in range(256)]
_new_tuple = tuple.__new__


class FastMessage(tuple[Any, ...]):
    """One decoded message: the payload values in wire order, then the frame.

    Generated subclasses (one per message) add a property per field.
    """

    __slots__ = ()
    _msgname: ClassVar[str] = ""
    _msgid: ClassVar[int] = -1
    fieldnames: ClassVar[tuple[str, ...]] = ()
    """Field names in declaration order, as pymavlink's ``fieldnames``."""

    def get_type(self) -> str:
        """The message name, e.g. ``"GLOBAL_POSITION_INT"``."""
        return self._msgname

    def get_msgId(self) -> int:
        """The message id."""
        return self._msgid

    def get_msgbuf(self) -> bytes | bytearray:
        """The whole frame, as it was decoded (signature included)."""
        frame: bytes | bytearray = self[-1]  # an annotation, not a cast: this runs per frame
        return frame

    def get_srcSystem(self) -> int:
        """The sender's system id."""
        frame = self[-1]
        return int(frame[5] if frame[0] == _STX_V2 else frame[3])

    def get_srcComponent(self) -> int:
        """The sender's component id."""
        frame = self[-1]
        return int(frame[6] if frame[0] == _STX_V2 else frame[4])

    def get_seq(self) -> int:
        """The frame's sequence number."""
        frame = self[-1]
        return int(frame[4] if frame[0] == _STX_V2 else frame[2])

    def __repr__(self) -> str:
        fields = ", ".join(f"{n}: {getattr(self, n)!r}" for n in self.fieldnames)
        return f"{self._msgname} {{{fields}}}"


#: Names a field may not have: FastMessage's own (a field may shadow tuple's count or index).
_RESERVED = frozenset(dir(FastMessage)) - frozenset(dir(tuple))


def _getter(
    at: int, field_type: str, array_length: int, *, chars_as_bytes: bool
) -> Callable[[FastMessage], Any]:
    """The accessor of a field stored from flat position ``at``, giving pymavlink's value."""
    if field_type == "char" and chars_as_bytes:
        return lambda m: m[at].rstrip(b"\x00")
    if field_type == "char":
        return lambda m: m[at].split(b"\x00", 1)[0].decode("ascii", "replace")
    if array_length > 1:
        end = at + array_length
        return lambda m: list(m[at:end])
    return cast("Callable[[FastMessage], Any]", itemgetter(at))


def message_class(message: MessageDef, *, chars_as_bytes: bool = False) -> type[FastMessage]:
    """A ``FastMessage`` subclass for ``message``, its fields read from the flat values.

    ``chars_as_bytes``: char fields are NUL-stripped bytes (the project's hand-written
    pymavlink classes) rather than pymavlink's generated ``str``.
    """
    namespace: dict[str, Any] = {
        "__slots__": (),
        "_msgname": message.name,
        "_msgid": message.msgid,
        "fieldnames": tuple(f.name for f in message.fields),
    }
    at = 0
    for f in message.wire_fields:
        if f.name in _RESERVED:
            raise ValueError(f"{message.name}.{f.name}: the name of a FastMessage method")
        getter = _getter(at, f.type, f.array_length, chars_as_bytes=chars_as_bytes)
        namespace[f.name] = property(getter)
        # A char array is one bytes value; any other array one value per element.
        at += 1 if f.type == "char" else max(f.array_length, 1)
    return type(f"Fast_{message.name}", (FastMessage,), namespace)


_Entry = tuple[Callable[..., tuple[Any, ...]], int, bytes, int, type[FastMessage]]


class FastDecoder:
    """Decodes frames of a chosen set of messages; see the module docstring."""

    __slots__ = ("_table", "messages")

    def __init__(
        self, messages: Iterable[MessageDef], *, chars_as_bytes: Collection[str] = ()
    ) -> None:
        """Decoders of ``messages``; those named in ``chars_as_bytes`` give char fields as
        bytes (see ``message_class``)."""
        self.messages: dict[int, MessageDef] = {}
        self._table: dict[int, _Entry] = {}
        for message in messages:
            unpacker = struct.Struct(message.struct_format)
            self.messages[message.msgid] = message
            self._table[message.msgid] = (
                unpacker.unpack_from,
                unpacker.size,
                bytes(unpacker.size),
                _REVERSED[message.crc_extra],
                message_class(message, chars_as_bytes=message.name in chars_as_bytes),
            )

    def __contains__(self, msgid: object) -> bool:
        return msgid in self._table

    def decode(self, frame: bytes | bytearray) -> FastMessage | None:
        """The message in ``frame`` (exactly one MAVLink frame); None if it is not ours.

        None: not a MAVLink frame header, or a message id outside this decoder's set (the
        caller hands the frame to pymavlink). ``Malformed``: one of our ids, but a length,
        incompatibility flag or CRC that pymavlink refuses too.
        """
        # The constants are literals here: this runs once per frame (0xFD: MAVLink 2, 0xFE:
        # MAVLink 1, flag 0x01: signed, 13 signature bytes; module docstring).
        size = len(frame)
        if size < 8:
            return None
        stx = frame[0]
        if stx == 0xFD:
            if size < 12:
                return None
            entry = self._table.get(frame[7] | frame[8] << 8 | frame[9] << 16)
            if entry is None:
                return None
            if frame[2] & 0xFE:
                raise Malformed(f"MAVLink 2 incompatibility flags 0x{frame[2]:02x}")
            start = 10
            end = 10 + frame[1]
            if size != end + (15 if frame[2] else 2):
                raise Malformed("MAVLink frame length differs from its header")
        elif stx == 0xFE:
            entry = self._table.get(frame[5])
            if entry is None:
                return None
            start = 6
            end = 6 + frame[1]
            if size != end + 2:
                raise Malformed("MAVLink frame length differs from its header")
        else:
            return None
        unpack, payload_size, zeros, extra, cls = entry
        # X.25 over header and payload, then CRC_EXTRA; compared bit-reversed (see _REVERSED).
        reversed_frame = frame.translate(_REVERSED)
        crc = crc_hqx(reversed_frame[1:end], 0xFFFF)
        if ((crc << 8) & 0xFFFF) ^ _CCITT[(crc >> 8) ^ extra] != (
            reversed_frame[end] << 8 | reversed_frame[end + 1]
        ):
            raise Malformed("MAVLink CRC does not match")
        # A tuple concatenated is built once; (*values, frame) goes through a list first.
        if end - start >= payload_size:
            return _new_tuple(cls, unpack(frame, start) + (frame,))  # noqa: RUF005
        # MAVLink 2 drops trailing zero bytes; a MAVLink 1 frame has no extensions.
        values = unpack(frame[start:end] + zeros[end - start :])
        return _new_tuple(cls, values + (frame,))  # noqa: RUF005

    def decode_payload(self, msgid: int, payload: bytes | bytearray) -> FastMessage | None:
        """Field values of a payload whose frame was checked elsewhere; None if not ours.

        The message's ``get_msgbuf`` and header accessors are unavailable (no frame).
        """
        entry = self._table.get(msgid)
        if entry is None:
            return None
        unpack, payload_size, zeros, _extra, cls = entry
        if len(payload) < payload_size:
            payload = bytes(payload) + zeros[len(payload) :]
        return _new_tuple(cls, (*unpack(payload, 0), b""))


def load_messages(names: Iterable[str]) -> list[MessageDef]:
    """The definitions of ``names`` from pymavlink's ardupilotmega XML and the project's.

    ``ValueError`` if a name is in neither or the XML breaks the MAVLink rules.
    """
    xml_dir = pymavlink_xml_dir()
    upstream = read_dialect(xml_dir / "ardupilotmega.xml")
    by_name = {m.name: m for m in upstream.values()}
    for msgid, message in read_dialect(_PROJECT_DIALECT, [xml_dir]).items():
        known = upstream.get(msgid)
        if known is None:
            by_name[message.name] = message
        elif known.name != message.name:
            raise ValueError(
                f"{message.source}: id {msgid} ({message.name}) is {known.name} upstream"
            )
    wanted = sorted(set(names))
    missing = [name for name in wanted if name not in by_name]
    if missing:
        raise ValueError(f"messages not in the dialect XML: {', '.join(missing)}")
    return [by_name[name] for name in wanted]


@cache
def default_decoder() -> FastDecoder:
    """The decoder of ``GATEWAY_MESSAGES``, built once per process.

    Empty (every frame goes to pymavlink) when the installed pymavlink is not
    ``PYMAVLINK_CHECKED``, when ``MAV_IGNORE_CRC`` tells pymavlink to take frames whatever
    their CRC, or when the XML cannot be read; a warning says why.
    """
    if os.environ.get("MAV_IGNORE_CRC"):
        log.warning("fastdecode_disabled", reason="mav_ignore_crc")
        return FastDecoder(())
    installed = metadata.version("pymavlink")
    if installed != PYMAVLINK_CHECKED:
        log.warning(
            "fastdecode_disabled",
            reason="pymavlink_version",
            installed=installed,
            checked=PYMAVLINK_CHECKED,
        )
        return FastDecoder(())
    try:
        messages = load_messages(GATEWAY_MESSAGES)
        own = {m.name for m in messages if m.source == _PROJECT_DIALECT.name}
        return FastDecoder(messages, chars_as_bytes=own)
    except ValueError as exc:
        log.warning("fastdecode_disabled", reason="dialect_xml", error=str(exc))
        return FastDecoder(())
