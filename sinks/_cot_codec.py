"""CoT encodings: XML, and TAK protocol v1 protobuf with mesh and stream framing.

The protobuf ``TakMessage`` is written by hand (a handful of fields, proto3 wire format), so
the tests' decoder (takproto) is independent of the encoder. Received CoT is validated by
``gateway.cot_validate``.
"""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from datetime import UTC, datetime

from sinks._cot_event import CotEvent

__all__ = ["mesh_frame", "stream_frame", "to_proto", "to_xml"]

_DECL = b'<?xml version="1.0" encoding="UTF-8" standalone="yes"?>\n'


def _time(value: datetime) -> str:
    utc = value.astimezone(UTC)
    return utc.strftime("%Y-%m-%dT%H:%M:%S.") + f"{utc.microsecond // 1000:03d}Z"


def _ms(value: datetime) -> int:
    return int(value.timestamp() * 1000)


def _float(value: float) -> str:
    return repr(float(value))


def to_xml(event: CotEvent) -> bytes:
    """The event as a CoT 2.0 XML document (declaration, newline, event; nothing after)."""
    root = ET.Element(
        "event",
        {
            "version": "2.0",
            "uid": event.uid,
            "type": event.type,
            "how": event.how,
            "time": _time(event.time),
            "start": _time(event.start),
            "stale": _time(event.stale),
        },
    )
    ET.SubElement(
        root,
        "point",
        {
            "lat": _float(event.lat),
            "lon": _float(event.lon),
            "hae": _float(event.hae),
            "ce": _float(event.ce),
            "le": _float(event.le),
        },
    )
    detail = ET.SubElement(root, "detail")
    if event.callsign is not None:
        contact = {"callsign": event.callsign}
        if event.endpoint:
            contact["endpoint"] = event.endpoint
        ET.SubElement(detail, "contact", contact)
    if event.course_deg is not None and event.speed_mps is not None:
        ET.SubElement(
            detail,
            "track",
            {"course": f"{event.course_deg:.2f}", "speed": f"{event.speed_mps:.2f}"},
        )
    if event.battery_pct is not None:
        ET.SubElement(detail, "status", {"battery": str(event.battery_pct)})
    if event.geopointsrc is not None:
        ET.SubElement(
            detail,
            "precisionlocation",
            {"geopointsrc": event.geopointsrc, "altsrc": event.altsrc or "???"},
        )
    if event.takv is not None:
        device, platform, os_name, version = event.takv
        ET.SubElement(
            detail,
            "takv",
            {"device": device, "platform": platform, "os": os_name, "version": version},
        )
    body = ET.tostring(root, encoding="unicode")
    if event.xml_detail:
        body = body.replace("</detail>", event.xml_detail + "</detail>", 1).replace(
            "<detail />", "<detail>" + event.xml_detail + "</detail>", 1
        )
    return _DECL + body.encode("utf-8")


# -- protobuf ------------------------------------------------------------------------------


def _varint(value: int) -> bytes:
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
    return _varint(field << 3 | wire)


def _str(field: int, value: str | None) -> bytes:
    if not value:
        return b""
    data = value.encode("utf-8")
    return _key(field, 2) + _varint(len(data)) + data


def _msg(field: int, payload: bytes) -> bytes:
    return _key(field, 2) + _varint(len(payload)) + payload


def _u64(field: int, value: int) -> bytes:
    return _key(field, 0) + _varint(value) if value else b""


def _double(field: int, value: float) -> bytes:
    return _key(field, 1) + struct.pack("<d", value) if value != 0.0 else b""


def to_proto(event: CotEvent) -> bytes:
    """The event as a serialized TAK protocol v1 ``TakMessage`` (without framing)."""
    detail = _str(1, _xml_detail_for_proto(event))
    if event.callsign is not None:
        detail += _msg(2, _str(1, event.endpoint) + _str(2, event.callsign))
    if event.geopointsrc is not None:
        detail += _msg(4, _str(1, event.geopointsrc) + _str(2, event.altsrc or "???"))
    if event.battery_pct is not None:
        detail += _msg(5, _u64(1, event.battery_pct))
    if event.takv is not None:
        device, platform, os_name, version = event.takv
        detail += _msg(6, _str(1, device) + _str(2, platform) + _str(3, os_name) + _str(4, version))
    if event.course_deg is not None and event.speed_mps is not None:
        detail += _msg(7, _double(1, event.speed_mps) + _double(2, event.course_deg))
    cot = (
        _str(1, event.type)
        + _str(5, event.uid)
        + _u64(6, _ms(event.time))
        + _u64(7, _ms(event.start))
        + _u64(8, _ms(event.stale))
        + _str(9, event.how)
        + _double(10, event.lat)
        + _double(11, event.lon)
        + _double(12, event.hae)
        + _double(13, event.ce)
        + _double(14, event.le)
        + _msg(15, detail)
    )
    return _msg(2, cot)


def _xml_detail_for_proto(event: CotEvent) -> str:
    # Everything not carried by a dedicated protobuf field travels as XML (uid, __group, ...).
    return event.xml_detail


def mesh_frame(message: bytes) -> bytes:
    """TAK protocol v1 mesh (UDP) framing: 0xBF, version 1, 0xBF, message."""
    return b"\xbf\x01\xbf" + message


def stream_frame(message: bytes) -> bytes:
    """TAK protocol v1 stream (TCP/TLS) framing: 0xBF, varint length, message."""
    return b"\xbf" + _varint(len(message)) + message
