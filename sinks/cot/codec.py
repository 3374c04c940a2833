"""CoT encodings: XML, and TAK protocol v1 protobuf in mesh (UDP) and stream (TCP/TLS) framing.

``Encoded`` holds one event's encodings, each made at most once however many destinations
want it. XML is written as the TAK servers expect on a stream and ATAK on the mesh: the XML
declaration, a newline, the event, and nothing after ``</event>``. Numbers are plain decimals
(the schema's ``xs:decimal`` has no exponent); times are UTC with milliseconds and ``Z``.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Literal

from sinks.cot.event import CotEvent, xml_attribute
from sinks.cot.proto import double, mesh_frame, message, stream_frame, string, uint

__all__ = ["Encoded", "Encoding", "cot_time", "decimal", "tak_control", "to_proto", "to_xml"]

Encoding = Literal["xml", "mesh", "stream"]

_DECLARATION = b'<?xml version="1.0" encoding="UTF-8" standalone="yes"?>\n'


_ZERO = timedelta(0)


def cot_time(value: datetime) -> str:
    """A CoT timestamp: UTC, milliseconds (truncated), ``Z``."""
    # Events read back from the spool carry pydantic's own UTC tzinfo, not datetime.UTC.
    utc = value if value.utcoffset() == _ZERO else value.astimezone(UTC)
    # isoformat cuts the microseconds to milliseconds as strftime's digits did (no rounding).
    return utc.replace(tzinfo=None).isoformat(timespec="milliseconds") + "Z"


_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_MS = timedelta(milliseconds=1)


def _ms(value: datetime) -> int:
    # Integer arithmetic: timestamp() * 1000 in floats can land a millisecond low.
    return (value - _EPOCH) // _MS


def decimal(value: float, places: int) -> str:
    """``value`` as an ``xs:decimal`` with at most ``places`` fraction digits, at least one."""
    text = f"{value:.{places}f}".rstrip("0")
    return text + "0" if text.endswith(".") else text


def _attrs(**values: str) -> str:
    return "".join(f" {k}={xml_attribute(v)}" for k, v in values.items())


def to_xml(event: CotEvent) -> bytes:
    """The event as one CoT 2.0 XML document: declaration, newline, event; nothing after."""
    head = _attrs(
        version="2.0",
        uid=event.uid,
        type=event.type,
        how=event.how,
        time=cot_time(event.time),
        start=cot_time(event.start),
        stale=cot_time(event.stale),
    )
    point = _attrs(
        lat=decimal(event.lat, 9),
        lon=decimal(event.lon, 9),
        hae=decimal(event.hae, 2),
        ce=decimal(event.ce, 2),
        le=decimal(event.le, 2),
    )
    detail = []
    if event.callsign is not None:
        endpoint = {"endpoint": event.endpoint} if event.endpoint else {}
        detail.append(f"<contact{_attrs(callsign=event.callsign, **endpoint)}/>")
    if event.group is not None:
        detail.append(f"<__group{_attrs(name=event.group[0], role=event.group[1])}/>")
    if event.course_deg is not None and event.speed_mps is not None:
        track = _attrs(course=decimal(event.course_deg, 2), speed=decimal(event.speed_mps, 2))
        detail.append(f"<track{track}/>")
    if event.battery_pct is not None:
        detail.append(f"<status{_attrs(battery=str(event.battery_pct))}/>")
    if event.geopointsrc is not None:
        source = _attrs(geopointsrc=event.geopointsrc, altsrc=event.altsrc or "???")
        detail.append(f"<precisionlocation{source}/>")
    if event.takv is not None:
        device, platform, os_name, version = event.takv
        takv = _attrs(device=device, platform=platform, os=os_name, version=version)
        detail.append(f"<takv{takv}/>")
    body = (
        f"<event{head}><point{point}/><detail>{''.join(detail)}{event.xml_detail}</detail></event>"
    )
    return _DECLARATION + body.encode("utf-8")


def to_proto(event: CotEvent) -> bytes:
    """The event as a serialized TAK protocol v1 ``TakMessage``, without framing."""
    detail = string(1, event.xml_detail)
    if event.callsign is not None:
        detail += message(2, string(1, event.endpoint) + string(2, event.callsign))
    if event.group is not None:
        detail += message(3, string(1, event.group[0]) + string(2, event.group[1]))
    if event.geopointsrc is not None:
        detail += message(4, string(1, event.geopointsrc) + string(2, event.altsrc or "???"))
    if event.battery_pct is not None:
        detail += message(5, uint(1, event.battery_pct))
    if event.takv is not None:
        device, platform, os_name, version = event.takv
        detail += message(
            6, string(1, device) + string(2, platform) + string(3, os_name) + string(4, version)
        )
    if event.course_deg is not None and event.speed_mps is not None:
        detail += message(7, double(1, event.speed_mps) + double(2, event.course_deg))
    cot = (
        string(1, event.type)
        + string(5, event.uid)
        + uint(6, _ms(event.time))
        + uint(7, _ms(event.start))
        + uint(8, _ms(event.stale))
        + string(9, event.how)
        + double(10, event.lat)
        + double(11, event.lon)
        + double(12, event.hae)
        + double(13, event.ce)
        + double(14, event.le)
        + message(15, detail)
    )
    return message(2, cot)


def tak_control(min_version: int = 1, max_version: int = 1, contact_uid: str = "") -> bytes:
    """``TakMessage`` field 1, a ``TakControl``: the protocol versions this sender speaks.

    On its own it is a control-only ``TakMessage``; put before a message's cotEvent field it
    rides along with that event (protobuf fields concatenate).
    """
    return message(1, uint(1, min_version) + uint(2, max_version) + string(3, contact_uid))


class Encoded:
    """One event and its encodings, each made on first request and then reused."""

    __slots__ = ("_cache", "_proto", "event")

    def __init__(self, event: CotEvent) -> None:
        self.event = event
        self._cache: dict[Encoding, bytes] = {}
        self._proto: bytes | None = None

    def proto(self) -> bytes:
        """The serialized ``TakMessage``, unframed (made once)."""
        if self._proto is None:
            self._proto = to_proto(self.event)
        return self._proto

    def mesh_with(self, prefix: bytes) -> bytes:
        """A mesh datagram whose ``TakMessage`` starts with ``prefix`` (a ``tak_control``)."""
        return mesh_frame(prefix + self.proto())

    def get(self, encoding: Encoding) -> bytes:
        """The event as XML, as a mesh datagram or as a stream frame."""
        data = self._cache.get(encoding)
        if data is None:
            if encoding == "xml":
                data = to_xml(self.event)
            else:
                proto = self.proto()
                data = mesh_frame(proto) if encoding == "mesh" else stream_frame(proto)
            self._cache[encoding] = data
        return data
