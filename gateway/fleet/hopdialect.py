"""The hop-schedule messages of the project dialect: FISCHER_HOP_SCHEDULE (61002),
FISCHER_HOP_SCHEDULE_ACK (61003) and FISCHER_HOP_EVENT (61004), added to pymavlink at import.

Defined here as pymavlink's generator would write them and registered in the
``ardupilotmega`` message map beside FISCHER_DETECTION (``gateway.fleet.dialect``).
``gateway/fleet/fischer_dialect.xml`` is the source of truth;
tests/gateway/fleet/test_hop_dialect.py checks these classes against what ``mavgen``
generates from it (same CRC_EXTRA, same bytes).
Each message's fields are declared in wire order (by type size), so the constructor takes
them in that order.

FISCHER_HOP_SCHEDULE: start_time_usec u64 (us), frequencies u64[8] (Hz), schedule_id u32,
bandwidth u32 (Hz), dwell u32 (ns), settle u32 (ns), target_system u8, target_component u8,
slot_count u8 (1..8).

FISCHER_HOP_SCHEDULE_ACK: schedule_id u32 (echoed), active_schedule_id u32, target_system
u8, target_component u8, result u8 (FISCHER_HOP_SCHEDULE_RESULT).

FISCHER_HOP_EVENT: time_usec u64 (us), frequency u64 (Hz), schedule_id u32, hop_count u32,
slot u8, reason u8 (FISCHER_HOP_REASON), rssi i8 (dBm), interference i8 (dBm); 127 is an
unknown power. docs/hopping.md has the protocol.
"""

from __future__ import annotations

import struct
from typing import Any, ClassVar

from pymavlink.dialects.v20 import ardupilotmega as _mav

__all__ = [
    "FISCHER_HOP_EVENT_CRC_EXTRA",
    "FISCHER_HOP_SCHEDULE_ACK_CRC_EXTRA",
    "FISCHER_HOP_SCHEDULE_CRC_EXTRA",
    "HOP_REASON_NAMES",
    "HOP_RESULT_ACCEPTED",
    "HOP_RESULT_DENIED",
    "HOP_RESULT_FAILED",
    "HOP_RESULT_NAMES",
    "HOP_RESULT_UNSUPPORTED_BANDWIDTH",
    "HOP_RESULT_UNSUPPORTED_DWELL",
    "HOP_RESULT_UNSUPPORTED_FREQUENCY",
    "MAVLINK_MSG_ID_FISCHER_HOP_EVENT",
    "MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE",
    "MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE_ACK",
    "POWER_UNKNOWN_DBM",
    "FischerHopEvent",
    "FischerHopSchedule",
    "FischerHopScheduleAck",
]

MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE = 61002
MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE_ACK = 61003
MAVLINK_MSG_ID_FISCHER_HOP_EVENT = 61004
#: CRC_EXTRA of each message, as mavgen computes it from the XML.
FISCHER_HOP_SCHEDULE_CRC_EXTRA = 16
FISCHER_HOP_SCHEDULE_ACK_CRC_EXTRA = 118
FISCHER_HOP_EVENT_CRC_EXTRA = 62

#: FISCHER_HOP_SCHEDULE_RESULT: only ACCEPTED means the airframe hops on the schedule.
HOP_RESULT_ACCEPTED = 0
HOP_RESULT_UNSUPPORTED_FREQUENCY = 1
HOP_RESULT_UNSUPPORTED_BANDWIDTH = 2
HOP_RESULT_UNSUPPORTED_DWELL = 3
HOP_RESULT_DENIED = 4
HOP_RESULT_FAILED = 5
HOP_RESULT_NAMES: dict[int, str] = {
    HOP_RESULT_ACCEPTED: "accepted",
    HOP_RESULT_UNSUPPORTED_FREQUENCY: "unsupported_frequency",
    HOP_RESULT_UNSUPPORTED_BANDWIDTH: "unsupported_bandwidth",
    HOP_RESULT_UNSUPPORTED_DWELL: "unsupported_dwell",
    HOP_RESULT_DENIED: "denied",
    HOP_RESULT_FAILED: "failed",
}
#: FISCHER_HOP_REASON.
HOP_REASON_NAMES: dict[int, str] = {0: "scheduled", 1: "jammed", 2: "interference"}
#: rssi / interference value that says the power is not known.
POWER_UNKNOWN_DBM = 127

_SLOTS = 8


class _Message(_mav.MAVLink_message):  # type: ignore[misc]
    """What pymavlink's generated classes share: the fields in wire order, no instance field."""

    fieldnames: ClassVar[list[str]]
    fielddisplays_by_name: ClassVar[dict[str, str]] = {}
    instance_field = None
    instance_offset = -1
    unpacker: ClassVar[struct.Struct]

    def __init__(self, *values: Any) -> None:
        _mav.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = self.fieldnames
        self._instance_field = None
        self._instance_offset = -1
        for name, value in zip(self.fieldnames, values, strict=True):
            setattr(self, name, value)

    def _values(self) -> list[Any]:
        return [getattr(self, name) for name in self.fieldnames]

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        """The frame bytes, as pymavlink packs every message."""
        payload = self.unpacker.pack(*self._values())
        return bytes(self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1))


class FischerHopSchedule(_Message):
    """The gateway's hop schedule for an airframe's radio (FISCHER_HOP_SCHEDULE)."""

    id = MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE
    msgname = "FISCHER_HOP_SCHEDULE"
    fieldnames: ClassVar[list[str]] = [
        "start_time_usec", "frequencies", "schedule_id", "bandwidth", "dwell", "settle",
        "target_system", "target_component", "slot_count",
    ]  # fmt: skip
    ordered_fieldnames = fieldnames
    fieldtypes: ClassVar[list[str]] = [
        "uint64_t", "uint64_t", "uint32_t", "uint32_t", "uint32_t", "uint32_t", "uint8_t",
        "uint8_t", "uint8_t",
    ]  # fmt: skip
    fieldenums_by_name: ClassVar[dict[str, str]] = {}
    fieldunits_by_name: ClassVar[dict[str, str]] = {
        "start_time_usec": "us", "frequencies": "Hz", "bandwidth": "Hz", "dwell": "ns",
        "settle": "ns",
    }  # fmt: skip
    native_format = bytearray(b"<QQIIIIBBB")
    orders: ClassVar[list[int]] = list(range(9))
    lengths: ClassVar[list[int]] = [1, _SLOTS, 1, 1, 1, 1, 1, 1, 1]
    array_lengths: ClassVar[list[int]] = [0, _SLOTS, 0, 0, 0, 0, 0, 0, 0]
    crc_extra = FISCHER_HOP_SCHEDULE_CRC_EXTRA
    unpacker = struct.Struct("<Q8QIIIIBBB")

    start_time_usec: int
    frequencies: list[int]
    schedule_id: int
    bandwidth: int
    dwell: int
    settle: int
    target_system: int
    target_component: int
    slot_count: int

    def _values(self) -> list[Any]:
        values = super()._values()
        return [values[0], *values[1], *values[2:]]


class FischerHopScheduleAck(_Message):
    """The airframe's answer to a schedule (FISCHER_HOP_SCHEDULE_ACK)."""

    id = MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE_ACK
    msgname = "FISCHER_HOP_SCHEDULE_ACK"
    fieldnames: ClassVar[list[str]] = [
        "schedule_id", "active_schedule_id", "target_system", "target_component", "result",
    ]  # fmt: skip
    ordered_fieldnames = fieldnames
    fieldtypes: ClassVar[list[str]] = ["uint32_t", "uint32_t", "uint8_t", "uint8_t", "uint8_t"]
    fieldenums_by_name: ClassVar[dict[str, str]] = {"result": "FISCHER_HOP_SCHEDULE_RESULT"}
    fieldunits_by_name: ClassVar[dict[str, str]] = {}
    native_format = bytearray(b"<IIBBB")
    orders: ClassVar[list[int]] = list(range(5))
    lengths: ClassVar[list[int]] = [1] * 5
    array_lengths: ClassVar[list[int]] = [0] * 5
    crc_extra = FISCHER_HOP_SCHEDULE_ACK_CRC_EXTRA
    unpacker = struct.Struct("<IIBBB")

    schedule_id: int
    active_schedule_id: int
    target_system: int
    target_component: int
    result: int


class FischerHopEvent(_Message):
    """One hop of the airframe's radio (FISCHER_HOP_EVENT)."""

    id = MAVLINK_MSG_ID_FISCHER_HOP_EVENT
    msgname = "FISCHER_HOP_EVENT"
    fieldnames: ClassVar[list[str]] = [
        "time_usec", "frequency", "schedule_id", "hop_count", "slot", "reason", "rssi",
        "interference",
    ]  # fmt: skip
    ordered_fieldnames = fieldnames
    fieldtypes: ClassVar[list[str]] = [
        "uint64_t", "uint64_t", "uint32_t", "uint32_t", "uint8_t", "uint8_t", "int8_t", "int8_t",
    ]  # fmt: skip
    fieldenums_by_name: ClassVar[dict[str, str]] = {"reason": "FISCHER_HOP_REASON"}
    fieldunits_by_name: ClassVar[dict[str, str]] = {
        "time_usec": "us", "frequency": "Hz", "rssi": "dBm", "interference": "dBm",
    }  # fmt: skip
    native_format = bytearray(b"<QQIIBBbb")
    orders: ClassVar[list[int]] = list(range(8))
    lengths: ClassVar[list[int]] = [1] * 8
    array_lengths: ClassVar[list[int]] = [0] * 8
    crc_extra = FISCHER_HOP_EVENT_CRC_EXTRA
    unpacker = struct.Struct("<QQIIBBbb")

    time_usec: int
    frequency: int
    schedule_id: int
    hop_count: int
    slot: int
    reason: int
    rssi: int
    interference: int


# Registered in the dialect pymavlink decodes with, so every parser in the process knows them.
for _cls in (FischerHopSchedule, FischerHopScheduleAck, FischerHopEvent):
    _mav.mavlink_map[_cls.id] = _cls
