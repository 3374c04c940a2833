"""Our CoT validator: what ATAK and the MITRE schema check and the available decoders do not.

takproto and cotdantic accept latitude 91 and a missing ``<point>``; ATAK drops such events.
``parse_cot`` reads one event, as XML or as TAK protocol v1 protobuf (mesh or one stream frame),
and refuses it with a ``CotError`` whose ``problem`` is a short code (for counters) and whose
message names the attribute. Checks: the seven event attributes present and non-blank,
``version`` ≥ 2, the ``type``/``how``/``qos`` patterns, UTC times ending in ``Z``, stale after
start, exactly one point whose five attributes are decimals (no NaN, no exponent), on the globe,
``ce``/``le`` not negative. ``strict=True`` adds the rules for what *we* emit: the XML
declaration first, nothing after ``</event>``, times with exactly milliseconds, no whitespace
in the uid.

XML is parsed with defusedxml (``forbid_dtd``, ``forbid_entities``, ``forbid_external``): a
DOCTYPE, an entity declaration or an external reference is refused before anything expands, and
nothing is ever fetched. Input size is bounded. Only ``CotError`` comes out of ``parse_cot``.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from enum import Enum
from typing import Literal

from defusedxml import DefusedXmlException
from defusedxml.ElementTree import fromstring

from gateway.errors import Malformed
from sinks.cot.proto import (
    MESH_HEADER,
    Fields,
    FieldValue,
    ProtoError,
    fixed64_double,
    mesh_payload,
    read_fields,
)

__all__ = [
    "MAX_EVENT_BYTES",
    "UNKNOWN",
    "CotError",
    "ParsedCot",
    "TakControl",
    "is_unknown",
    "parse_cot",
    "scan_control",
]

#: CoT's "unknown" for hae, ce and le (ATAK ``CotPoint.UNKNOWN``).
UNKNOWN = 9999999.0
#: Largest event ``parse_cot`` reads.
MAX_EVENT_BYTES = 64 * 1024

_TYPE = re.compile(r"\w+(-\w+)*(;[^;]*)?")
_HOW = re.compile(r"\w(-\w+)*")
_QOS = re.compile(r"\d-\w-\w", re.ASCII)
_VERSION = re.compile(r"\d+(\.\d*)?", re.ASCII)
_DECIMAL = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)", re.ASCII)
_TIME = re.compile(r"(\d{4})-(\d\d)-(\d\d)T(\d\d):(\d\d):(\d\d)(\.\d{1,9})?Z", re.ASCII)
_MS_TIME = re.compile(r".*T\d\d:\d\d:\d\d\.\d{3}Z", re.ASCII)
_REQUIRED = ("version", "uid", "type", "how", "time", "start", "stale")
_POINT = ("lat", "lon", "hae", "ce", "le")


class CotError(Malformed):
    """Raised by ``parse_cot`` for bytes that are not a valid CoT event.

    ``problem`` is a short, fixed code for counting (``xml``, ``dtd``, ``protobuf``,
    ``not_event``, ``attribute``, ``type``, ``how``, ``time``, ``stale``, ``point``,
    ``position``, ``oversize``, ``framing``, ...); the message names the attribute and value.
    """

    def __init__(self, problem: str, message: str) -> None:
        self.problem = problem
        super().__init__(message)


@dataclass(frozen=True, slots=True)
class ParsedCot:
    """A CoT event that passed validation: the fields a consumer needs."""

    uid: str
    type: str
    how: str
    time: datetime
    start: datetime
    stale: datetime
    lat: float
    lon: float
    hae: float
    ce: float
    le: float
    callsign: str
    encoding: Literal["xml", "protobuf"]


def is_unknown(value: float) -> bool:
    """True for CoT's "unknown" sentinel (9999999.0 or more)."""
    return value >= UNKNOWN


def parse_cot(data: bytes, *, strict: bool = False) -> ParsedCot:
    """Parse and validate one CoT event (XML, or TAK protobuf if it starts with ``0xbf``).

    Raises ``CotError`` naming the problem, and nothing else, whatever ``data`` holds.
    """
    if len(data) > MAX_EVENT_BYTES:
        raise CotError("oversize", f"event of {len(data)} bytes exceeds {MAX_EVENT_BYTES}")
    if data[:1] == MESH_HEADER[:1]:
        return _parse_protobuf(data)
    return _parse_xml(data, strict=strict)


# -- XML -----------------------------------------------------------------------------------


def _parse_xml(data: bytes, *, strict: bool) -> ParsedCot:
    if strict and not data.startswith(b"<?xml "):
        raise CotError("framing", "the XML declaration must come first")
    if strict and not data.endswith(b"</event>"):
        raise CotError("framing", "nothing may follow </event>")
    try:
        root = fromstring(data, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except DefusedXmlException as exc:
        raise CotError("dtd", f"DTDs, entities and external references are refused: {exc}") from exc
    except (ET.ParseError, ValueError, LookupError) as exc:
        # ValueError/LookupError: an encoding declaration Python does not know.
        raise CotError("xml", f"not well-formed XML: {exc}") from exc
    if root.tag != "event":
        raise CotError("root", f"root element is <{root.tag}>, expected <event>")
    attrs = root.attrib
    for name in _REQUIRED:
        if not attrs.get(name, "").strip():
            raise CotError("attribute", f"event attribute {name!r} is missing or blank")
    version = attrs["version"]
    if not _VERSION.fullmatch(version) or float(version) < 2:
        raise CotError("version", f"version {version!r} is not a decimal ≥ 2")
    if "qos" in attrs and not _QOS.fullmatch(attrs["qos"]):
        raise CotError("qos", f"qos {attrs['qos']!r} does not match digit-char-char")
    if strict:
        for name in ("time", "start", "stale"):
            if not _MS_TIME.fullmatch(attrs[name]):
                raise CotError("time", f"{name} {attrs[name]!r} lacks exactly 3 fraction digits")
    times = [_xml_time(attrs[name], name) for name in ("time", "start", "stale")]
    points = root.findall("point")
    if len(points) != 1:
        raise CotError("point", f"expected exactly one <point>, found {len(points)}")
    values = [_xml_decimal(points[0].attrib.get(name), name) for name in _POINT]
    contact = root.find("detail/contact")
    callsign = contact.attrib.get("callsign", "") if contact is not None else ""
    return _checked(
        attrs["uid"], attrs["type"], attrs["how"], times, values, callsign, "xml", strict
    )


def _xml_time(text: str, name: str) -> datetime:
    match = _TIME.fullmatch(text)
    if match is None:
        raise CotError("time", f"{name} {text!r} is not a UTC time ending in Z")
    year, month, day, hour, minute, second = (int(g) for g in match.groups()[:6])
    fraction = match.group(7) or ".0"
    try:
        value = datetime(year, month, day, hour, minute, second, tzinfo=UTC)
    except ValueError as exc:
        raise CotError("time", f"{name} {text!r} is not a calendar time: {exc}") from exc
    return value + timedelta(microseconds=int((fraction[1:] + "000000")[:6]))


def _xml_decimal(raw: str | None, name: str) -> float:
    if raw is None or not _DECIMAL.fullmatch(raw):
        raise CotError("point", f"point {name} {raw!r} is not a decimal number")
    value = float(raw)
    if not math.isfinite(value):
        raise CotError("point", f"point {name} {raw!r} is out of range")
    return value


# -- TAK protocol v1 -----------------------------------------------------------------------


def _parse_protobuf(data: bytes) -> ParsedCot:
    try:
        message = read_fields(mesh_payload(data))
        if 2 not in message:
            raise CotError("not_event", "TakMessage carries no cotEvent (a TakControl only)")
        event = read_fields(_bytes(message, 2, "cotEvent"))
        uid, type_, how = (
            _text(event, n, name) for n, name in ((5, "uid"), (1, "type"), (9, "how"))
        )
        times = [_ms(event, n, name) for n, name in ((6, "time"), (7, "start"), (8, "stale"))]
        values = [_double(event, n, name) for n, name in zip(range(10, 15), _POINT, strict=True)]
        callsign = ""
        if 15 in event:
            detail = read_fields(_bytes(event, 15, "detail"))
            if 2 in detail:
                callsign = _text(read_fields(_bytes(detail, 2, "contact")), 2, "callsign")
    except ProtoError as exc:
        raise CotError("protobuf", f"not a TAK protocol v1 message: {exc}") from exc
    return _checked(uid, type_, how, times, values, callsign, "protobuf", False)


def _last(fields: Fields, number: int) -> FieldValue | None:
    values = fields.get(number)
    return values[-1] if values else None


def _bytes(fields: Fields, number: int, name: str) -> bytes:
    value = _last(fields, number)
    if not isinstance(value, bytes):
        raise ProtoError(f"{name} is not a length-delimited field")
    return value


def _text(fields: Fields, number: int, name: str) -> str:
    if number not in fields:
        return ""
    try:
        return _bytes(fields, number, name).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ProtoError(f"{name} is not UTF-8") from exc


def _ms(fields: Fields, number: int, name: str) -> datetime:
    value = _last(fields, number)
    if not isinstance(value, int) or value <= 0:
        raise CotError("time", f"{name} is missing")
    try:
        return datetime(1970, 1, 1, tzinfo=UTC) + timedelta(milliseconds=value)
    except OverflowError as exc:
        raise CotError("time", f"{name} {value} ms is out of range") from exc


def _double(fields: Fields, number: int, name: str) -> float:
    value = _last(fields, number)
    result = 0.0 if value is None else fixed64_double(value, name)  # proto3 default
    if not math.isfinite(result):
        raise CotError("point", f"point {name} is not a number")
    return result


# -- rules shared by both encodings --------------------------------------------------------


def _checked(
    uid: str,
    type_: str,
    how: str,
    times: list[datetime],
    values: list[float],
    callsign: str,
    encoding: Literal["xml", "protobuf"],
    strict: bool,
) -> ParsedCot:
    if not uid.strip():
        raise CotError("attribute", "uid is missing or blank")
    if strict and any(c.isspace() for c in uid):
        raise CotError("uid", f"uid {uid!r} contains whitespace")
    if not _TYPE.fullmatch(type_):
        raise CotError("type", f"type {type_!r} does not match the CoT type pattern")
    if not _HOW.fullmatch(how):
        raise CotError("how", f"how {how!r} does not match the CoT how pattern")
    time, start, stale = times
    if stale <= start:
        raise CotError("stale", f"stale {stale.isoformat()} is not after start")
    lat, lon, hae, ce, le = values
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise CotError("position", f"point {lat},{lon} is off the globe")
    if ce < 0 or le < 0:
        raise CotError("point", f"ce {ce} or le {le} is negative")
    return ParsedCot(uid, type_, how, time, start, stale, lat, lon, hae, ce, le, callsign, encoding)


# -- TAK protocol negotiation events -------------------------------------------------------


class TakControl(Enum):
    """What a TAK server's control event says, for the client side of the negotiation."""

    NONE = "none"
    OFFER_V1 = "offer_v1"
    ACCEPTED = "accepted"
    REFUSED = "refused"


def scan_control(data: bytes) -> TakControl:
    """Classify one XML event from a TAK server: a v1 offer, a response, or neither.

    ``t-x-takp-v`` with ``<TakProtocolSupport version="1"/>`` is an offer of version 1;
    ``t-x-takp-r`` with ``<TakResponse status="true"/>`` accepts our request, any other
    ``t-x-takp-r`` refuses it. Never raises: anything unreadable is ``NONE``.
    """
    if b"t-x-takp-" not in data or len(data) > MAX_EVENT_BYTES:
        return TakControl.NONE
    try:
        root = fromstring(data.strip(), forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except (DefusedXmlException, ET.ParseError, ValueError, LookupError):
        return TakControl.NONE
    kind = root.attrib.get("type", "")
    if kind == "t-x-takp-v":
        versions = {e.attrib.get("version", "").strip() for e in root.iter("TakProtocolSupport")}
        return TakControl.OFFER_V1 if "1" in versions else TakControl.NONE
    if kind == "t-x-takp-r":
        statuses = [e.attrib.get("status", "") for e in root.iter("TakResponse")]
        accepted = bool(statuses) and statuses[0].strip().lower() == "true"
        return TakControl.ACCEPTED if accepted else TakControl.REFUSED
    return TakControl.NONE
