"""The simulated airframe: frames that pymavlink decodes, the circle, the rates, UDP delivery."""

from __future__ import annotations

import math
from collections import Counter
from functools import partial
from typing import Any

import anyio
import anyio.abc
import pytest
from geographiclib.geodesic import Geodesic  # type: ignore[import-untyped]
from pymavlink.dialects.v20 import ardupilotmega as apm

from gateway.sim.airframe import SimProfile, SimulatedAirframe
from gateway.sim.demofleet import build_demo_fleet, run_fleet

LAP_S = 2 * math.pi * 400.0 / 22.0


def decode(frames: list[bytes]) -> list[Any]:
    """Decode with a fresh pymavlink parser (CRC checked), one message per frame."""
    parser = apm.MAVLink(None)
    messages = []
    for frame in frames:
        decoded = parser.parse_buffer(frame)
        assert decoded is not None
        assert len(decoded) == 1
        assert decoded[0].get_type() != "BAD_DATA"
        messages.append(decoded[0])
    return messages


def fly(sim: SimulatedAirframe, until_s: float, step_s: float) -> list[Any]:
    """Call ``frames_at`` every ``step_s`` over ``[0, until_s)`` and decode everything."""
    frames = []
    for i in range(round(until_s / step_s)):
        frames.extend(sim.frames_at(i * step_s))
    return decode(frames)


def frames_until(sim: SimulatedAirframe, duration_s: float) -> list[bytes]:
    """What ``run_udp`` sends over ``duration_s`` of sim time, computed without I/O."""
    frames: list[bytes] = []
    t_s = 0.0
    while t_s <= duration_s + 1e-9:
        frames.extend(sim.frames_at(t_s))
        t_s = sim.next_due_s()
    return frames


def by_type(messages: list[Any], name: str) -> list[Any]:
    return [m for m in messages if m.get_type() == name]


class TestFrames:
    """Every frame is MAVLink 2 that pymavlink decodes with the values the profile implies."""

    def test_first_call_sends_every_message_once_in_order(self) -> None:
        frames = SimulatedAirframe(7).frames_at(0.0)
        messages = decode(frames)
        assert [m.get_type() for m in messages] == [
            "HEARTBEAT",
            "GLOBAL_POSITION_INT",
            "ATTITUDE",
            "GPS_RAW_INT",
            "VFR_HUD",
            "SYS_STATUS",
            "BATTERY_STATUS",
        ]
        assert all(frame[0] == 0xFD for frame in frames)
        assert [m.get_seq() for m in messages] == list(range(7))
        assert {(m.get_srcSystem(), m.get_srcComponent()) for m in messages} == {(7, 1)}

    def test_heartbeat_is_an_armed_fixed_wing_ardupilot_in_guided(self) -> None:
        (hb,) = by_type(decode(SimulatedAirframe(1).frames_at(0.0)), "HEARTBEAT")
        assert hb.type == apm.MAV_TYPE_FIXED_WING
        assert hb.autopilot == apm.MAV_AUTOPILOT_ARDUPILOTMEGA
        assert hb.base_mode & apm.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.base_mode & apm.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert hb.custom_mode == 15
        assert hb.system_status == apm.MAV_STATE_ACTIVE
        assert hb.mavlink_version == 3

    def test_positions_lie_on_the_circle_for_a_whole_lap(self) -> None:
        sim = SimulatedAirframe(1, phase_rad=0.3)
        positions = by_type(fly(sim, LAP_S, 0.1), "GLOBAL_POSITION_INT")
        assert len(positions) == len(sim.sent_positions) == round(LAP_S / 0.1)
        bearings = []
        for msg in positions:
            inverse = Geodesic.WGS84.Inverse(65.8252, 21.6886, msg.lat / 1e7, msg.lon / 1e7)
            assert inverse["s12"] == pytest.approx(400.0, abs=0.5)
            bearings.append(inverse["azi1"] % 360)
        # One lap passes every bearing from the centre.
        assert {int(b // 30) for b in bearings} == set(range(12))

    def test_velocity_heading_and_attitude_match_a_coordinated_right_turn(self) -> None:
        sim = SimulatedAirframe(1)
        messages = fly(sim, 10.0, 0.1)
        positions = by_type(messages, "GLOBAL_POSITION_INT")
        attitudes = by_type(messages, "ATTITUDE")
        bank = math.atan(22.0**2 / (400.0 * 9.80665))
        chord_m = 2 * 400.0 * math.sin(22.0 / 400.0 / 2)  # one second along the circle
        for before, after, att in zip(positions, positions[10:], attitudes, strict=False):
            assert math.hypot(before.vx, before.vy) == pytest.approx(2200, abs=2)
            assert before.vz == 0
            assert math.degrees(math.atan2(before.vy, before.vx)) % 360 == pytest.approx(
                before.hdg / 100, abs=0.05
            )
            # It moves where its heading points: a chord turned by half the turn in between.
            moved = Geodesic.WGS84.Inverse(
                before.lat / 1e7, before.lon / 1e7, after.lat / 1e7, after.lon / 1e7
            )
            assert moved["s12"] == pytest.approx(chord_m, abs=0.05)
            half_turn_deg = math.degrees(22.0 / 400.0) / 2
            assert moved["azi1"] % 360 == pytest.approx(
                (before.hdg / 100 + half_turn_deg) % 360, abs=0.1
            )
            # Right wing down in a clockwise (right) turn; yaw is the heading.
            assert att.time_boot_ms == before.time_boot_ms
            assert att.roll == pytest.approx(bank, abs=1e-6)
            assert math.degrees(att.yaw) % 360 == pytest.approx(before.hdg / 100, abs=0.01)
            assert att.yawspeed == pytest.approx(22.0 / 400.0 * math.cos(bank), rel=1e-5)
            assert before.alt == 250_000
            assert before.relative_alt == 100_000

    def test_gps_carries_the_mavlink2_extensions_and_agrees_with_the_position(self) -> None:
        messages = decode(SimulatedAirframe(1).frames_at(12.5))
        (gpi,) = by_type(messages, "GLOBAL_POSITION_INT")
        (gps,) = by_type(messages, "GPS_RAW_INT")
        (hud,) = by_type(messages, "VFR_HUD")
        assert gps.fix_type == apm.GPS_FIX_TYPE_3D_FIX
        assert (gps.lat, gps.lon, gps.alt) == (gpi.lat, gpi.lon, gpi.alt)
        assert gps.alt_ellipsoid == 250_000 + 22_000
        assert gps.h_acc > 0
        assert gps.vel == 2200
        assert gps.cog == gpi.hdg
        assert gps.time_usec == 12_500_000
        assert hud.groundspeed == pytest.approx(22.0)
        assert hud.heading == round(gpi.hdg / 100) % 360
        assert hud.alt == pytest.approx(250.0)

    def test_battery_drains_at_the_profile_power(self) -> None:
        sim = SimulatedAirframe(1, SimProfile(power_w=355.0, battery_wh=600.0))
        full = decode(sim.frames_at(0.0))
        hour = decode(sim.frames_at(3600.0))
        (status0,), (battery0,) = by_type(full, "SYS_STATUS"), by_type(full, "BATTERY_STATUS")
        (status1,), (battery1,) = by_type(hour, "SYS_STATUS"), by_type(hour, "BATTERY_STATUS")
        assert (status0.battery_remaining, battery0.battery_remaining) == (100, 100)
        assert battery0.energy_consumed == 0
        assert battery0.time_remaining == round(600 / 355 * 3600)
        # One hour at 355 W is 355 Wh = 12 780 hJ, leaving 245 Wh.
        assert battery1.energy_consumed == 12_780
        assert status1.battery_remaining == battery1.battery_remaining == round(100 * 245 / 600)
        assert battery1.time_remaining == round(245 / 355 * 3600)
        for status in (status0, status1):
            watts = status.voltage_battery / 1000 * status.current_battery / 100
            assert watts == pytest.approx(355.0, rel=0.01)
        assert status1.voltage_battery < status0.voltage_battery
        assert battery1.current_consumed > battery0.current_consumed == 0
        assert battery1.voltages[0] * 6 == pytest.approx(status1.voltage_battery, abs=6)

    def test_same_inputs_give_the_same_bytes(self) -> None:
        a, b = SimulatedAirframe(3, phase_rad=1.0), SimulatedAirframe(3, phase_rad=1.0)
        times = [i * 0.05 for i in range(200)]
        assert [a.frames_at(t) for t in times] == [b.frames_at(t) for t in times]


class TestSchedule:
    """Each message group is sent at its rate, whatever the calling step."""

    @pytest.mark.parametrize("step_s", [0.001, 0.03, 0.05])
    def test_rates_over_ten_seconds(self, step_s: float) -> None:
        counts = Counter(m.get_type() for m in fly(SimulatedAirframe(1), 10.0, step_s))
        assert counts == {
            "HEARTBEAT": 10,
            "GLOBAL_POSITION_INT": 100,
            "ATTITUDE": 100,
            "GPS_RAW_INT": 50,
            "VFR_HUD": 50,
            "SYS_STATUS": 20,
            "BATTERY_STATUS": 20,
        }

    def test_a_gap_skips_missed_slots_instead_of_bursting(self) -> None:
        sim = SimulatedAirframe(1)
        assert len(sim.frames_at(0.0)) == 7
        assert len(sim.frames_at(100.0)) == 7
        assert sim.frames_at(100.05) == []
        assert sim.next_due_s() == pytest.approx(100.1)

    def test_sequence_numbers_wrap_at_256(self) -> None:
        messages = fly(SimulatedAirframe(1), 10.0, 0.05)
        assert [m.get_seq() for m in messages] == [i % 256 for i in range(len(messages))]

    def test_a_zero_rate_turns_a_group_off(self) -> None:
        profile = SimProfile(position_hz=0, gps_hz=0, status_hz=0, heartbeat_hz=0)
        sim = SimulatedAirframe(1, profile)
        assert sim.frames_at(0.0) == []
        assert sim.next_due_s() == math.inf

    @pytest.mark.parametrize(
        ("field", "value"),
        [("radius_m", 0.0), ("speed_mps", -1.0), ("gps_hz", -1.0), ("alt_msl_m", math.nan)],
    )
    def test_profile_rejects_values_out_of_range(self, field: str, value: float) -> None:
        with pytest.raises(ValueError, match=f"SimProfile.{field}"):
            SimProfile(**{field: value})

    def test_sysid_must_fit_mavlink(self) -> None:
        with pytest.raises(ValueError, match="sysid"):
            SimulatedAirframe(256)


def test_demo_fleet_has_distinct_airframes_near_boden() -> None:
    fleet = build_demo_fleet(3)
    assert [a.sysid for a in fleet] == [1, 2, 3]
    first = [decode(a.frames_at(0.0))[1] for a in fleet]
    assert [m.get_srcSystem() for m in first] == [1, 2, 3]
    assert len({(m.lat, m.lon) for m in first}) == 3
    for m in first:
        assert Geodesic.WGS84.Inverse(65.8252, 21.6886, m.lat / 1e7, m.lon / 1e7)["s12"] < 5_000


async def receive(sock: anyio.abc.UDPSocket, count: int) -> list[bytes]:
    return [(await sock.receive())[0] for _ in range(count)]


@pytest.mark.anyio
class TestUdp:
    """``run_udp`` and ``run_fleet`` deliver the frames to real loopback sockets."""

    async def test_run_udp_delivers_every_frame_byte_identical_and_paced(self) -> None:
        expected = frames_until(SimulatedAirframe(4), 1.0)
        sim = SimulatedAirframe(4)
        with anyio.fail_after(5):
            async with await anyio.create_udp_socket(local_host="127.0.0.1") as sock:
                port = sock.extra(anyio.abc.SocketAttribute.local_port)
                async with anyio.create_task_group() as tg:
                    start = anyio.current_time()
                    await tg.start(
                        partial(sim.run_udp, "127.0.0.1", port, duration_s=1.0, speed=10.0)
                    )
                    received = await receive(sock, len(expected))
                elapsed = anyio.current_time() - start
        assert received == expected
        assert sim.frames_sent == len(expected)
        assert [p.time_boot_ms for p in sim.sent_positions] == list(range(0, 1001, 100))
        # Paced, not sent at once: 1 s of flight at 10x takes 0.1 s (uvloop's clock is in
        # milliseconds, so allow one).
        assert elapsed >= 1.0 / 10.0 - 0.002

    async def test_run_udp_stops_on_cancel(self) -> None:
        sim = SimulatedAirframe(1)
        with anyio.fail_after(5):
            async with await anyio.create_udp_socket(local_host="127.0.0.1") as sock:
                port = sock.extra(anyio.abc.SocketAttribute.local_port)
                async with anyio.create_task_group() as tg:
                    await tg.start(partial(sim.run_udp, "127.0.0.1", port, speed=50.0))
                    received = await receive(sock, 20)
                    tg.cancel_scope.cancel()
        assert len(received) == 20
        assert sim.frames_sent >= 20

    async def test_run_udp_keeps_flying_when_nobody_listens(self) -> None:
        async with await anyio.create_udp_socket(local_host="127.0.0.1") as closed:
            port = closed.extra(anyio.abc.SocketAttribute.local_port)
        sim = SimulatedAirframe(1)
        with anyio.fail_after(5):
            await sim.run_udp("127.0.0.1", port, duration_s=2.0, speed=100.0)
        assert sim.frames_sent == len(frames_until(SimulatedAirframe(1), 2.0))

    async def test_run_fleet_sends_each_airframe_to_its_port(self) -> None:
        fleet = build_demo_fleet(2)
        twins = build_demo_fleet(2)
        with anyio.fail_after(5):
            async with (
                await anyio.create_udp_socket(local_host="127.0.0.1") as one,
                await anyio.create_udp_socket(local_host="127.0.0.1") as two,
            ):
                ports = [s.extra(anyio.abc.SocketAttribute.local_port) for s in (one, two)]
                async with anyio.create_task_group() as tg:
                    await tg.start(
                        partial(run_fleet, fleet, "127.0.0.1", ports, duration_s=0.5, speed=10.0)
                    )
                    got = [
                        await receive(one, len(frames_until(twins[0], 0.5))),
                        await receive(two, len(frames_until(twins[1], 0.5))),
                    ]
        for sysid, frames in enumerate(got, start=1):
            assert {m.get_srcSystem() for m in decode(frames)} == {sysid}
        assert [a.frames_sent for a in fleet] == [len(frames) for frames in got]

    async def test_run_fleet_needs_a_port_per_airframe(self) -> None:
        with pytest.raises(ValueError, match="2 airframes but 1 ports"):
            await run_fleet(build_demo_fleet(2), "127.0.0.1", [14550], duration_s=0.1)

    async def test_run_udp_rejects_a_bad_speed(self) -> None:
        with pytest.raises(ValueError, match="speed"):
            await SimulatedAirframe(1).run_udp("127.0.0.1", 14550, speed=0.0)
