"""FISCHER_HOP_SCHEDULE, FISCHER_HOP_SCHEDULE_ACK and FISCHER_HOP_EVENT: our message classes
against the module mavgen generates from gateway/fleet/fischer_dialect.xml, both ways."""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest
from ack_peer import generate_dialect
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as apm

from gateway.fleet.hopdialect import (
    FISCHER_HOP_EVENT_CRC_EXTRA,
    FISCHER_HOP_SCHEDULE_ACK_CRC_EXTRA,
    FISCHER_HOP_SCHEDULE_CRC_EXTRA,
    HOP_REASON_NAMES,
    HOP_RESULT_NAMES,
    FischerHopEvent,
    FischerHopSchedule,
    FischerHopScheduleAck,
)
from gateway.fleet.mavlink import MavlinkParser


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """The dialect module mavgen makes from gateway/fleet/fischer_dialect.xml: the oracle."""
    return generate_dialect(tmp_path_factory.mktemp("mavgen"))


FREQS = [2_405_000_000, 2_420_000_000, 2_435_000_000, 5_800_000_000, 0, 0, 0, 0]
SCHEDULE = (1_763_800_000_000_000, FREQS, 0xDEADBEEF, 10_000_000, 12_000, 0, 12, 1, 4)
ACK = (0xDEADBEEF, 0xDEADBEEF, 255, 191, 0)
EVENT = (1_763_800_000_123_456, 5_800_000_000, 0xDEADBEEF, 4_000_000_001, 3, 1, -61, 127)

CASES = [
    ("fischer_hop_schedule", FischerHopSchedule, SCHEDULE, FISCHER_HOP_SCHEDULE_CRC_EXTRA),
    ("fischer_hop_schedule_ack", FischerHopScheduleAck, ACK, FISCHER_HOP_SCHEDULE_ACK_CRC_EXTRA),
    ("fischer_hop_event", FischerHopEvent, EVENT, FISCHER_HOP_EVENT_CRC_EXTRA),
]


@pytest.mark.parametrize(("name", "ours", "args", "crc"), CASES)
def test_definition_matches_mavgen(
    generated: ModuleType, name: str, ours: type[Any], args: tuple[Any, ...], crc: int
) -> None:
    theirs = getattr(generated, f"MAVLink_{name}_message")
    assert (theirs.id, theirs.msgname, theirs.crc_extra) == (ours.id, ours.msgname, crc)
    assert theirs.fieldnames == ours.fieldnames
    assert theirs.ordered_fieldnames == ours.ordered_fieldnames
    assert theirs.fieldtypes == ours.fieldtypes
    assert theirs.unpacker.format == ours.unpacker.format
    assert (theirs.orders, theirs.lengths, theirs.array_lengths) == (
        ours.orders,
        ours.lengths,
        ours.array_lengths,
    )
    assert theirs.fieldunits_by_name == ours.fieldunits_by_name
    assert theirs.fieldenums_by_name == ours.fieldenums_by_name


@pytest.mark.parametrize(("name", "ours", "args", "crc"), CASES)
def test_bytes_match_mavgen_and_each_decodes_the_other(
    generated: ModuleType, name: str, ours: type[Any], args: tuple[Any, ...], crc: int
) -> None:
    del crc
    theirs = generated.MAVLink(None, srcSystem=7, srcComponent=1)
    expected = bytes(getattr(theirs, f"{name}_encode")(*args).pack(theirs))
    frame = ours(*args).pack(apm.MAVLink(None, srcSystem=7, srcComponent=1))
    assert frame == expected
    (back,) = generated.MAVLink(None).parse_buffer(frame)
    assert [getattr(back, f) for f in ours.fieldnames] == list(args)
    (mine,) = MavlinkParser(fast=True).feed(expected, whole=True)  # fleet.fastdecode
    assert mine.get_type() == name.upper()
    assert [getattr(mine, f) for f in ours.fieldnames] == list(args)


def test_enums_match_the_xml(generated: ModuleType) -> None:
    results = generated.enums["FISCHER_HOP_SCHEDULE_RESULT"]
    assert {k: v.name for k, v in results.items() if k in HOP_RESULT_NAMES} == {
        k: "FISCHER_HOP_SCHEDULE_RESULT_" + v.upper() for k, v in HOP_RESULT_NAMES.items()
    }
    reasons = generated.enums["FISCHER_HOP_REASON"]
    assert {k: v.name for k, v in reasons.items() if k in HOP_REASON_NAMES} == {
        k: "FISCHER_HOP_REASON_" + v.upper() for k, v in HOP_REASON_NAMES.items()
    }


u8 = st.integers(0, 255)
u32 = st.integers(0, 2**32 - 1)
u64 = st.integers(0, 2**64 - 1)
i8 = st.integers(-128, 127)


@settings(max_examples=150, deadline=None)
@given(
    schedule=st.tuples(u64, st.lists(u64, min_size=8, max_size=8), u32, u32, u32, u32, u8, u8, u8),
    event=st.tuples(u64, u64, u32, u32, u8, u8, i8, i8),
    ack=st.tuples(u32, u32, u8, u8, u8),
)
def test_any_values_round_trip_through_mavgen(
    generated: ModuleType,
    schedule: tuple[Any, ...],
    event: tuple[Any, ...],
    ack: tuple[Any, ...],
) -> None:
    """Any in-range values: the same bytes as mavgen, and read back unchanged by both."""
    theirs = generated.MAVLink(None, srcSystem=1, srcComponent=1)
    mine = apm.MAVLink(None, srcSystem=1, srcComponent=1)
    for cls, args in ((FischerHopSchedule, schedule), (FischerHopEvent, event)):
        name = cls.msgname.lower()
        frame = cls(*args).pack(mine)
        assert frame == bytes(getattr(theirs, f"{name}_encode")(*args).pack(theirs))
        (back,) = MavlinkParser().feed(frame, whole=True)
        assert [getattr(back, f) for f in cls.fieldnames] == list(args)
    frame = FischerHopScheduleAck(*ack).pack(mine)
    (theirs_back,) = generated.MAVLink(None).parse_buffer(frame)
    assert [getattr(theirs_back, f) for f in FischerHopScheduleAck.fieldnames] == list(ack)
