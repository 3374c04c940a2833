"""The passthrough's command policy and its framing, unit by unit and under fuzzing.

The policy (gateway/fleet/uplinkpolicy.py) is an allowlist; the passthrough relays only
frames it re-serialised from parsed fields. These tests drive ``Passthrough.receive`` with
arbitrary bytes and with well-formed frames of every message id the dialect knows (fields
random), and read what would reach the airframe with pymavlink, an independent parser.
"""

from __future__ import annotations

import hashlib
import re
import time
from pathlib import Path
from typing import Any

import anyio
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as m

from gateway.config import PassthroughConfig
from gateway.fleet.passthrough import Passthrough
from gateway.fleet.security.signing import mavlink_timestamp_now
from gateway.fleet.uplinkpolicy import (
    COMMANDS,
    EFFECTOR_COMMANDS,
    GATEWAY_ONLY,
    MISSION_ITEMS,
    RELAYED,
    SIGNED_ONLY_COMMANDS,
    check,
)

ROOT = Path(__file__).resolve().parents[3]
KEY = hashlib.sha256(b"unit-test-station").digest()
PEER = ("127.0.0.1", 40000)


def station(key: bytes | None = None) -> Any:
    gcs = m.MAVLink(None, srcSystem=255, srcComponent=190)
    if key is not None:
        gcs.signing.secret_key = key
        gcs.signing.sign_outgoing = True
        gcs.signing.timestamp = mavlink_timestamp_now(time.time()) + 1000
    return gcs


def parsed(frame: bytes) -> Any:
    msg = m.MAVLink(None).parse_char(frame)
    assert msg is not None
    return msg


def make(uplink: str, sent: list[bytes]) -> Passthrough:
    async def to_airframe(_airframe: str, frames: bytes) -> None:
        sent.append(frames)

    extra = {"key_file": "/unused"} if uplink == "signed" else {}
    config = PassthroughConfig.model_validate(
        {"uri": "udp://127.0.0.1:0", "uplink": uplink, "param_set_allow": ["MPC_*"], **extra}
    )
    return Passthrough("F26E-001", 1, config, to_airframe, gcs_key=KEY)


def feed(passthrough: Passthrough, *datagrams: bytes) -> None:
    async def main() -> None:
        for data in datagrams:
            await passthrough.receive(PEER, data)

    anyio.run(main)


class TestPolicy:
    """Deny by default: what is not listed is refused, effectors whatever the mode."""

    @pytest.mark.parametrize("uplink", ["none", "signed", "open"])
    @pytest.mark.parametrize("command", sorted(EFFECTOR_COMMANDS))
    def test_every_effector_command_is_refused_in_every_mode(
        self, uplink: Any, command: int
    ) -> None:
        gcs = station()
        for msg in (
            gcs.command_long_encode(1, 1, command, 0, 9, 1900, 0, 0, 0, 0, 0),
            gcs.command_int_encode(1, 1, 0, command, 0, 0, 9, 1900, 0, 0, 0, 0, 0),
            gcs.mission_item_int_encode(1, 1, 0, 0, command, 0, 1, 9, 1900, 0, 0, 0, 0, 0, 0),
            gcs.mission_item_encode(1, 1, 0, 0, command, 0, 1, 9, 1900, 0, 0, 0, 0, 0),
        ):
            refusal = check(parsed(bytes(msg.pack(gcs))), sysid=1, uplink=uplink)
            assert refusal is not None
            assert refusal.reason in ("effector", "uplink_none")

    def test_arming_termination_and_reboot_need_a_signed_uplink(self) -> None:
        gcs = station()
        for command in SIGNED_ONLY_COMMANDS:
            msg = parsed(
                bytes(gcs.command_long_encode(1, 1, command, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs))
            )
            assert check(msg, sysid=1, uplink="signed") is None
            refusal = check(msg, sysid=1, uplink="open")
            assert refusal is not None
            assert refusal.reason == "signed_only"
        armed_mode = parsed(bytes(gcs.set_mode_encode(1, 128 | 1, 0).pack(gcs)))
        assert check(armed_mode, sysid=1, uplink="open") is not None
        assert check(armed_mode, sysid=1, uplink="signed") is None

    def test_a_base_mode_outside_a_byte_counts_as_armed(self) -> None:
        """1e10 has no armed bit in Python but an ARM core saturates it to 0xFF in C."""
        gcs = station()
        for base_mode in (1e10, 2.0**32 + 1, 1.5e9, -128.0, 256.0, float("nan"), float("inf")):
            for msg in (
                gcs.command_long_encode(1, 1, 176, 0, base_mode, 4, 0, 0, 0, 0, 0),
                gcs.command_int_encode(1, 1, 0, 176, 0, 0, base_mode, 4, 0, 0, 0, 0, 0),
            ):
                frame = parsed(bytes(msg.pack(gcs)))
                refusal = check(frame, sysid=1, uplink="open")
                assert refusal is not None, base_mode
                assert refusal.reason == "signed_only"
                assert check(frame, sysid=1, uplink="signed") is None
        plain = gcs.command_long_encode(1, 1, 176, 0, 1.0, 4, 0, 0, 0, 0, 0)
        assert check(parsed(bytes(plain.pack(gcs))), sysid=1, uplink="open") is None

    def test_flight_and_read_commands_pass_and_the_lists_do_not_overlap(self) -> None:
        gcs = station()
        for command in COMMANDS - {179}:  # DO_SET_HOME: a safety setting (TestSafetySettings)
            msg = parsed(
                bytes(gcs.command_long_encode(1, 1, command, 0, 1, 4, 4, 0, 0, 0, 0).pack(gcs))
            )
            assert check(msg, sysid=1, uplink="open") is None, command
        assert not COMMANDS & EFFECTOR_COMMANDS
        assert not COMMANDS & SIGNED_ONLY_COMMANDS
        assert not MISSION_ITEMS & EFFECTOR_COMMANDS
        assert not RELAYED & set(GATEWAY_ONLY)

    def test_parameters_only_from_the_allow_list_and_never_outputs(self) -> None:
        gcs = station()

        def param(name: bytes) -> Any:
            return parsed(bytes(gcs.param_set_encode(1, 1, name, 1.0, 9).pack(gcs)))

        allow = ("MPC_*", "SERVO*")
        assert check(param(b"MPC_XY_CRUISE"), sysid=1, uplink="open", param_set_allow=allow) is None
        names = (b"SERVO9_FUNCTION", b"RELAY_PIN", b"RC9_OPTION", b"NAV_RCL_ACT")
        # ArduPilot finds some names whatever their case: so does the never-list.
        lower = (b"servo9_function", b"Relay_Pin", b"rc9_option")
        for name in names[:3] + lower:
            refusal = check(param(name), sysid=1, uplink="signed", param_set_allow=("*",))
            assert refusal is not None, name
            assert refusal.reason == "parameter"
        for name in names:
            refusal = check(param(name), sysid=1, uplink="signed", param_set_allow=allow)
            assert refusal is not None
            assert refusal.reason == "parameter"

    def test_commands_for_another_system_are_refused(self) -> None:
        gcs = station()
        msg = parsed(bytes(gcs.command_long_encode(7, 1, 512, 0, 33, 0, 0, 0, 0, 0, 0).pack(gcs)))
        refusal = check(msg, sysid=1, uplink="open")
        assert refusal is not None
        assert refusal.reason == "wrong_target"
        broadcast = parsed(bytes(gcs.param_request_list_encode(0, 0).pack(gcs)))
        assert check(broadcast, sysid=1, uplink="open") is None


class TestDocs:
    """docs/security.md shows the table the code enforces."""

    def test_the_documented_table_is_the_code(self) -> None:
        text = (ROOT / "docs" / "security.md").read_text()
        section = text.split("### The command policy", 1)[1].split("\n## ", 1)[0]

        def numbers(row: str) -> set[int]:
            line = next(x for x in section.splitlines() if x.startswith(f"| {row} |"))
            return {int(n) for n in re.findall(r"\b(\d+)\b", line.split("|")[2])}

        assert numbers("relayed messages") == set(RELAYED)
        assert numbers("commands") == set(COMMANDS)
        assert numbers("signed uplink only") == set(SIGNED_ONLY_COMMANDS)
        assert numbers("mission items") == set(MISSION_ITEMS)
        assert numbers("effectors (named in refusals)") == set(EFFECTOR_COMMANDS)
        assert numbers("gateway only") == set(GATEWAY_ONLY)


def relayed_messages(sent: list[bytes]) -> list[Any]:
    """What reached the airframe, read by pymavlink: whole v2 frames with a good CRC only."""
    out = []
    for frames in sent:
        reader = m.MAVLink(None)
        msgs = reader.parse_buffer(frames) or []
        assert reader.buf_len() == 0
        for msg in msgs:
            assert msg.get_type() != "BAD_DATA"
            assert frames[0] == 0xFD
            assert not msg.get_signed()
            out.append(msg)
    return out


known_ids = sorted(i for i in m.mavlink_map if i not in GATEWAY_ONLY)


@st.composite
def wellformed(draw: st.DrawFn) -> bytes:
    """A MAVLink 2 frame of a known id, random payload, right CRC: the parser reads it."""
    msgid = draw(st.sampled_from(known_ids))
    cls = m.mavlink_map[msgid]
    payload = draw(st.binary(min_size=1, max_size=cls.unpacker.size))
    header = bytes([0xFD, len(payload), 0, 0, draw(st.integers(0, 255)), 255, 190])
    body = header + msgid.to_bytes(3, "little") + payload
    crc = m.x25crc(body[1:])
    crc.accumulate(bytes([cls.crc_extra]))
    return body + crc.crc.to_bytes(2, "little")


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(st.binary(max_size=600), wellformed()), min_size=1, max_size=8))
def test_no_bytes_raise_and_only_allowed_rebuilt_frames_reach_the_airframe(
    datagrams: list[bytes],
) -> None:
    sent: list[bytes] = []
    passthrough = make("open", sent)
    feed(passthrough, *datagrams)
    for msg in relayed_messages(sent):
        assert check(msg, sysid=1, uplink="open", param_set_allow=("MPC_*",)) is None
    assert passthrough.refused["internal_error"] == 0


@settings(max_examples=100, deadline=None)
@given(st.lists(st.one_of(st.binary(max_size=300), wellformed()), min_size=1, max_size=6))
def test_a_signed_uplink_relays_nothing_unsigned(datagrams: list[bytes]) -> None:
    sent: list[bytes] = []
    passthrough = make("signed", sent)
    feed(passthrough, *datagrams)
    assert sent == []
    assert passthrough.refused["internal_error"] == 0


def test_a_signed_heartbeat_is_rebuilt_unsigned_for_the_link_to_sign() -> None:
    sent: list[bytes] = []
    passthrough = make("signed", sent)
    gcs = station(KEY)
    frame = bytes(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs))
    feed(passthrough, frame, frame)  # the second is a replay
    (msg,) = relayed_messages(sent)
    assert msg.get_type() == "HEARTBEAT"
    assert (msg.get_srcSystem(), msg.get_srcComponent()) == (255, 190)
    assert passthrough.refused["signature_replay"] == 1
    wrong = station(hashlib.sha256(b"another").digest())
    feed(passthrough, bytes(wrong.heartbeat_encode(6, 8, 0, 0, 4).pack(wrong)))
    assert passthrough.refused["signature_auth"] == 1
    assert len(sent) == 1


def test_a_flood_from_strangers_leaves_room_for_a_proven_station() -> None:
    """Senders that proved nothing fill at most 192 of the 256 queued datagrams: a local
    flood without the key cannot crowd out the signed station's commands."""
    passthrough = make("signed", [])
    station, stranger = ("127.0.0.1", 40001), ("127.0.0.1", 40002)
    passthrough.link.learn_peer(station)
    send, receive = anyio.create_memory_object_stream[tuple[tuple[str, int], bytes]](256)
    passthrough._send = send  # the queue run() makes, without its consumer
    with send, receive:
        for _ in range(1000):
            passthrough._from_gcs("gcs", stranger, b"junk")
        assert send.statistics().current_buffer_used == 192
        for _ in range(10):
            passthrough._from_gcs("gcs", station, b"command")
        assert send.statistics().current_buffer_used == 202
        assert passthrough.uplink_dropped == 1000 - 192


class TestSafetySettings:
    """What changes the airframe's own safety needs a signed station (the cold run's finds)."""

    @pytest.mark.parametrize(
        "build",
        [
            lambda g: g.mission_count_encode(1, 1, 4, 1),  # a new geofence
            lambda g: g.mission_clear_all_encode(1, 1, 2),  # rally points cleared
            lambda g: g.mission_clear_all_encode(1, 1, 255),  # everything cleared
            lambda g: g.mission_item_int_encode(1, 1, 0, 0, 5001, 0, 1, 4, 0, 0, 0, 0, 0, 0, 1),
            lambda g: g.command_long_encode(1, 1, 179, 0, 0, 0, 0, 0, 65.0, 21.0, 0),
            lambda g: g.mission_item_int_encode(1, 1, 0, 0, 179, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0),
            lambda g: g.request_data_stream_encode(0, 0, 0, 0, 0),  # stop every stream
            lambda g: g.command_long_encode(1, 1, 511, 0, 33, -1, 0, 0, 0, 0, 0),
            lambda g: g.set_mode_encode(1, 32 | 1, 0),  # hardware in the loop
            lambda g: g.command_long_encode(1, 1, 176, 0, 2 | 1, 4, 4, 0, 0, 0, 0),  # test flag
        ],
    )
    def test_refused_from_an_open_station_relayed_from_a_signed_one(self, build: Any) -> None:
        gcs = station()
        msg = parsed(bytes(build(gcs).pack(gcs)))
        refusal = check(msg, sysid=1, uplink="open")
        assert refusal is not None
        assert refusal.reason == "signed_only"
        assert check(msg, sysid=1, uplink="signed") is None

    def test_a_mission_and_a_stream_request_still_pass_from_an_open_station(self) -> None:
        gcs = station()
        for msg in (
            gcs.mission_count_encode(1, 1, 4, 0),
            gcs.mission_clear_all_encode(1, 1, 0),
            gcs.request_data_stream_encode(0, 0, 0, 4, 1),
            gcs.command_long_encode(1, 1, 511, 0, 33, 200000, 0, 0, 0, 0, 0),
            gcs.command_ack_encode(76, 0, 0, 0, 0, 0),  # no target: an extension left out
        ):
            assert check(parsed(bytes(msg.pack(gcs))), sysid=1, uplink="open") is None

    @pytest.mark.parametrize(
        "name", [b"AFS_TERMINATE", b"ARMING_REQUIRE", b"brd_safety_deflt", b"CBRK_IO_SAFETY"]
    )
    def test_parameters_that_arm_or_terminate_are_never_set(self, name: bytes) -> None:
        gcs = station()
        msg = parsed(bytes(gcs.param_set_encode(1, 1, name, 0, 9).pack(gcs)))
        refusal = check(msg, sysid=1, uplink="signed", param_set_allow=("*",))
        assert refusal is not None
        assert refusal.reason == "parameter"
