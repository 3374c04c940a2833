"""The project's MAVLink dialect: FISCHER_DETECTION (61000) and FISCHER_DETECTION_ACK (61001),
added to pymavlink at import.

No upstream dialect has an object-detection message (common.xml and ardupilotmega.xml have
none), so the airframes send ours. It is defined here as pymavlink's generator would write
it, and registered in the ``ardupilotmega`` dialect's message map, so one parser reads
common, ArduPilot and our messages. ``gateway/fleet/fischer_dialect.xml`` is the source of truth;
the tests check these classes against the module ``mavgen`` generates from that XML (same
CRC_EXTRA, same bytes).

FISCHER_DETECTION wire order (sorted by size, then the extension): time_usec u64,
detection_id u32, lat i32, lon i32 (degE7), alt_msl f32 (m), sigma_h f32 (m), class_id u16,
sensor u8, confidence u8 (%), then the extensions subtype char[16] and frame_size u8 (the
detections in this sensor frame, 0: unknown).

FISCHER_DETECTION_ACK wire order: time_usec u64, detection_id u32 (the detection's identity,
echoed), target_system u8, target_component u8, result u8 (FISCHER_DETECTION_ACK_RESULT: 0
HELD, 1 DUPLICATE; both mean "stop re-sending"). docs/detection-ack.md has the protocol.
"""

from __future__ import annotations

import struct
from typing import Any, ClassVar

from pymavlink.dialects.v20 import ardupilotmega as _mav

__all__ = [
    "ACK_RESULT_NAMES",
    "CLASS_NAMES",
    "FISCHER_DETECTION_ACK_CRC_EXTRA",
    "FISCHER_DETECTION_ACK_RESULT_DUPLICATE",
    "FISCHER_DETECTION_ACK_RESULT_HELD",
    "FISCHER_DETECTION_CRC_EXTRA",
    "MAVLINK_MSG_ID_FISCHER_DETECTION",
    "MAVLINK_MSG_ID_FISCHER_DETECTION_ACK",
    "SENSOR_NAMES",
    "FischerDetection",
    "FischerDetectionAck",
    "fischer_detection",
    "fischer_detection_ack",
]

MAVLINK_MSG_ID_FISCHER_DETECTION = 61000
#: CRC_EXTRA of the base fields (what mavgen computes from dialect/fischer.xml).
FISCHER_DETECTION_CRC_EXTRA = 20
#: class_id → object class, as the airframes' classifier numbers them.
CLASS_NAMES: dict[int, str] = {
    1: "tank",
    2: "armour",
    3: "infantry_platoon",
    4: "uav",
    5: "loitering_munition",
}
#: FISCHER_SENSOR enum.
SENSOR_NAMES: dict[int, str] = {0: "eo", 1: "ir", 2: "rf"}

MAVLINK_MSG_ID_FISCHER_DETECTION_ACK = 61001
#: CRC_EXTRA of FISCHER_DETECTION_ACK (what mavgen computes from the XML).
FISCHER_DETECTION_ACK_CRC_EXTRA = 224
#: FISCHER_DETECTION_ACK_RESULT enum: the detection is now held in the gateway's spool ...
FISCHER_DETECTION_ACK_RESULT_HELD = 0
#: ... or was already held (this copy was a re-send). Both mean "stop re-sending".
FISCHER_DETECTION_ACK_RESULT_DUPLICATE = 1
ACK_RESULT_NAMES: dict[int, str] = {
    FISCHER_DETECTION_ACK_RESULT_HELD: "held",
    FISCHER_DETECTION_ACK_RESULT_DUPLICATE: "duplicate",
}


class FischerDetection(_mav.MAVLink_message):  # type: ignore[misc]
    """One object detection (FISCHER_DETECTION)."""

    id = MAVLINK_MSG_ID_FISCHER_DETECTION
    msgname = "FISCHER_DETECTION"
    fieldnames: ClassVar[list[str]] = [
        "time_usec", "detection_id", "lat", "lon", "alt_msl", "sigma_h", "class_id", "sensor",
        "confidence", "subtype", "frame_size",
    ]  # fmt: skip
    ordered_fieldnames = fieldnames
    fieldtypes: ClassVar[list[str]] = [
        "uint64_t", "uint32_t", "int32_t", "int32_t", "float", "float", "uint16_t", "uint8_t",
        "uint8_t", "char", "uint8_t",
    ]  # fmt: skip
    fielddisplays_by_name: ClassVar[dict[str, str]] = {}
    fieldenums_by_name: ClassVar[dict[str, str]] = {"sensor": "FISCHER_SENSOR"}
    fieldunits_by_name: ClassVar[dict[str, str]] = {
        "time_usec": "us", "lat": "degE7", "lon": "degE7", "alt_msl": "m", "sigma_h": "m",
        "confidence": "%",
    }  # fmt: skip
    native_format = bytearray(b"<QIiiffHBBcB")
    orders: ClassVar[list[int]] = list(range(11))
    lengths: ClassVar[list[int]] = [1] * 11
    array_lengths: ClassVar[list[int]] = [0] * 9 + [16, 0]
    crc_extra = FISCHER_DETECTION_CRC_EXTRA
    unpacker = struct.Struct("<QIiiffHBB16sB")
    instance_field = None
    instance_offset = -1

    def __init__(
        self,
        time_usec: int,
        detection_id: int,
        lat: int,
        lon: int,
        alt_msl: float,
        sigma_h: float,
        class_id: int,
        sensor: int,
        confidence: int,
        subtype: bytes = b"",
        frame_size: int = 0,
    ) -> None:
        _mav.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = self.fieldnames
        self._instance_field = None
        self._instance_offset = -1
        self.time_usec = time_usec
        self.detection_id = detection_id
        self.lat = lat
        self.lon = lon
        self.alt_msl = alt_msl
        self.sigma_h = sigma_h
        self.class_id = class_id
        self.sensor = sensor
        self.confidence = confidence
        self.subtype = subtype
        self.frame_size = frame_size

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        """The frame bytes, as pymavlink packs every message."""
        payload = self.unpacker.pack(
            self.time_usec, self.detection_id, self.lat, self.lon, self.alt_msl, self.sigma_h,
            self.class_id, self.sensor, self.confidence, self.subtype, self.frame_size,
        )  # fmt: skip
        return bytes(self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


def fischer_detection(
    time_usec: int,
    detection_id: int,
    lat_e7: int,
    lon_e7: int,
    alt_msl_m: float,
    sigma_h_m: float,
    class_id: int,
    sensor: int,
    confidence_pct: int,
    subtype: str = "",
    frame_size: int = 0,
) -> FischerDetection:
    """A FISCHER_DETECTION message, ready to ``pack``; ``frame_size`` is the number of
    detections in its sensor frame (0: unknown)."""
    return FischerDetection(
        time_usec, detection_id, lat_e7, lon_e7, alt_msl_m, sigma_h_m, class_id, sensor,
        confidence_pct, subtype.encode("ascii")[:16], frame_size,
    )  # fmt: skip


class FischerDetectionAck(_mav.MAVLink_message):  # type: ignore[misc]
    """The gateway's acknowledgement of one detection (FISCHER_DETECTION_ACK)."""

    id = MAVLINK_MSG_ID_FISCHER_DETECTION_ACK
    msgname = "FISCHER_DETECTION_ACK"
    fieldnames: ClassVar[list[str]] = [
        "time_usec", "detection_id", "target_system", "target_component", "result",
    ]  # fmt: skip
    ordered_fieldnames = fieldnames
    fieldtypes: ClassVar[list[str]] = ["uint64_t", "uint32_t", "uint8_t", "uint8_t", "uint8_t"]
    fielddisplays_by_name: ClassVar[dict[str, str]] = {}
    fieldenums_by_name: ClassVar[dict[str, str]] = {"result": "FISCHER_DETECTION_ACK_RESULT"}
    fieldunits_by_name: ClassVar[dict[str, str]] = {"time_usec": "us"}
    native_format = bytearray(b"<QIBBB")
    orders: ClassVar[list[int]] = list(range(5))
    lengths: ClassVar[list[int]] = [1] * 5
    array_lengths: ClassVar[list[int]] = [0] * 5
    crc_extra = FISCHER_DETECTION_ACK_CRC_EXTRA
    unpacker = struct.Struct("<QIBBB")
    instance_field = None
    instance_offset = -1

    def __init__(
        self,
        time_usec: int,
        detection_id: int,
        target_system: int,
        target_component: int,
        result: int,
    ) -> None:
        _mav.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = self.fieldnames
        self._instance_field = None
        self._instance_offset = -1
        self.time_usec = time_usec
        self.detection_id = detection_id
        self.target_system = target_system
        self.target_component = target_component
        self.result = result

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        """The frame bytes, as pymavlink packs every message."""
        payload = self.unpacker.pack(
            self.time_usec, self.detection_id, self.target_system, self.target_component,
            self.result,
        )  # fmt: skip
        return bytes(self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


def fischer_detection_ack(
    time_usec: int,
    detection_id: int,
    target_system: int,
    target_component: int,
    result: int = FISCHER_DETECTION_ACK_RESULT_HELD,
) -> FischerDetectionAck:
    """A FISCHER_DETECTION_ACK for the detection (``detection_id``, ``time_usec``) of
    ``target_system``/``target_component``, ready to ``pack``."""
    return FischerDetectionAck(time_usec, detection_id, target_system, target_component, result)


# Registered in the dialect pymavlink decodes with, so every parser in the process knows them.
_mav.mavlink_map[MAVLINK_MSG_ID_FISCHER_DETECTION] = FischerDetection
_mav.mavlink_map[MAVLINK_MSG_ID_FISCHER_DETECTION_ACK] = FischerDetectionAck
