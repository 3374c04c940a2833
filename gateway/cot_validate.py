"""Validating received Cursor-on-Target XML: what receivers check and decoders do not.

takproto accepts latitude 91 and a missing point; ATAK drops such events. This validator
refuses them with an error naming the problem: every event attribute present and non-blank,
the type and how patterns, UTC times ending in Z, stale after start, exactly one point with
five numeric attributes on the globe. DOCTYPEs and entities are refused outright and the
size is bounded, so a hostile sender cannot expand or exhaust the parser.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from datetime import UTC, datetime

from gateway.errors import FrameError

__all__ = ["MAX_EVENT_BYTES", "UNKNOWN", "CotError", "ParsedCot", "is_unknown", "parse_cot"]

UNKNOWN = 9999999.0
_TYPE = re.compile(r"^\w+(-\w+)*(;[^;]*)?$")
_HOW = re.compile(r"^\w(-\w+)*$")
_TIME = re.compile(r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}(\.\d{1,9})?Z$")
MAX_EVENT_BYTES = 64 * 1024


class CotError(FrameError):
    """Raised for bytes that are not a valid CoT event; names what was wrong."""

    reason = "malformed"


class ParsedCot:
    """A validated CoT event as received: the fields a consumer needs."""

    __slots__ = ("callsign", "ce", "hae", "how", "lat", "lon", "stale", "time", "type", "uid")

    def __init__(self, root: ET.Element) -> None:
        self.uid = root.attrib["uid"]
        self.type = root.attrib["type"]
        self.how = root.attrib["how"]
        self.time = _parse_time(root.attrib["time"], "time")
        self.stale = _parse_time(root.attrib["stale"], "stale")
        point = root.find("point")
        assert point is not None  # noqa: S101 - checked by parse_cot
        self.lat = float(point.attrib["lat"])
        self.lon = float(point.attrib["lon"])
        self.ce = float(point.attrib["ce"])
        self.hae = float(point.attrib["hae"])
        contact = root.find("detail/contact")
        self.callsign = contact.attrib.get("callsign", "") if contact is not None else ""


def _parse_time(text: str, name: str) -> datetime:
    if not _TIME.match(text):
        raise CotError(f"{name} {text!r} is not a UTC time ending in Z")
    head, _, frac = text[:-1].partition(".")
    value = datetime.strptime(head, "%Y-%m-%dT%H:%M:%S").replace(tzinfo=UTC)
    if frac:
        value = value.replace(microsecond=int((frac + "000000")[:6]))
    return value


def parse_cot(data: bytes) -> ParsedCot:
    """Parse and validate one CoT XML event; raise ``CotError`` naming the problem."""
    if len(data) > MAX_EVENT_BYTES:
        raise CotError(f"event of {len(data)} bytes exceeds {MAX_EVENT_BYTES}")
    if b"<!DOCTYPE" in data or b"<!ENTITY" in data:
        raise CotError("DOCTYPE and entities are refused")
    try:
        root = ET.fromstring(data)  # noqa: S314 - no DTDs (refused above), bounded size
    except ET.ParseError as exc:
        raise CotError(f"not well-formed XML: {exc}") from exc
    if root.tag != "event":
        raise CotError(f"root element is <{root.tag}>, expected <event>")
    for name in ("version", "uid", "type", "how", "time", "start", "stale"):
        if not root.attrib.get(name, "").strip():
            raise CotError(f"event attribute {name!r} is missing or blank")
    if not _TYPE.match(root.attrib["type"]):
        raise CotError(f"type {root.attrib['type']!r} does not match the CoT pattern")
    if not _HOW.match(root.attrib["how"]):
        raise CotError(f"how {root.attrib['how']!r} does not match the CoT pattern")
    points = root.findall("point")
    if len(points) != 1:
        raise CotError(f"expected exactly one <point>, found {len(points)}")
    for name in ("lat", "lon", "hae", "ce", "le"):
        raw = points[0].attrib.get(name)
        try:
            value = float(raw) if raw is not None else math.nan
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise CotError(f"point {name} {raw!r} is not a number")
    parsed = ParsedCot(root)
    if not -90.0 <= parsed.lat <= 90.0 or not -180.0 <= parsed.lon <= 180.0:
        raise CotError(f"point {parsed.lat},{parsed.lon} is off the globe")
    start = _parse_time(root.attrib["start"], "start")
    if parsed.stale <= start:
        raise CotError("stale is not after start")
    if parsed.ce < 0:
        raise CotError("ce is negative")
    return parsed


def is_unknown(value: float) -> bool:
    """True for CoT's 'unknown' sentinel (9999999.0)."""
    return value >= UNKNOWN
