"""The passthrough's guard against FISCHER_HOP_SCHEDULE from a local process
(gateway/fleet/passthrough.py ``gateway_only_frame``), over arbitrary bytes."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as apm

from gateway.fleet.hopdialect import MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE, FischerHopSchedule
from gateway.fleet.passthrough import gateway_only_frame

u32 = st.integers(0, 2**32 - 1)


def schedule_frame(sid: int, freq: int) -> bytes:
    gcs = apm.MAVLink(None, srcSystem=255, srcComponent=190)
    return bytes(FischerHopSchedule(0, [freq] + [0] * 7, sid, 1, 1, 0, 1, 0, 1).pack(gcs))


@given(st.binary(max_size=600), st.integers(0, 600))
def test_any_bytes_are_looked_at_without_an_error(data: bytes, start: int) -> None:
    found = gateway_only_frame(data, start)
    assert found in (None, MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE)


@given(st.binary(max_size=300), st.binary(max_size=300), u32, u32)
def test_a_schedule_anywhere_in_a_datagram_is_found(
    before: bytes, after: bytes, sid: int, freq: int
) -> None:
    data = before + schedule_frame(sid, freq) + after
    assert gateway_only_frame(data) == MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE
    # Completing bytes already forwarded: found when it ends in the new part only.
    frame = schedule_frame(sid, freq)
    assert gateway_only_frame(frame, len(frame) - 1) == MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE
    assert gateway_only_frame(frame + after, len(frame)) in (
        None,
        MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE,  # ``after`` may hold another one by chance
    )


def test_other_frames_pass_and_a_bad_crc_does_not_hide_a_schedule() -> None:
    """A signed link recomputes the CRC of what it signs: a bad one proves nothing."""
    gcs = apm.MAVLink(None, srcSystem=255, srcComponent=190)
    heartbeat = bytes(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs))
    assert gateway_only_frame(heartbeat * 3) is None
    broken = bytearray(schedule_frame(5, 2_405_000_000))
    broken[-1] ^= 0xFF
    assert gateway_only_frame(heartbeat + bytes(broken)) == MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE
