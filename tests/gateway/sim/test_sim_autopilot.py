"""The simulated autopilot: modes and command answers as PX4 and ArduPilot give them, and the
mission flown with its own kinematics, so telemetry, the camera and detections follow it.

Uplink messages go through the wire (a pymavlink ground station packs, the airframe's own
parser reads) into ``SimulatedAirframe.answer``; time is sim time, stepped by the test.
"""

from __future__ import annotations

import math
import socket
from typing import Any

import anyio
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.domain.geodesy import distance_bearing
from gateway.sim.airframe import SimProfile, SimulatedAirframe
from gateway.sim.autopilot import EFFECTOR_COMMANDS
from gateway.sim.runner import DetectionFeed
from gateway.sim.scenario import load_scenario_text

PX4_LOITER = 4 << 16 | 3 << 24
PX4_MISSION = 4 << 16 | 4 << 24
PX4_RTL = 4 << 16 | 5 << 24
POINT = (65.8400, 21.7000)
CENTRE = (65.8252, 21.6886)  # the default orbit's centre: home


class Gcs:
    """A ground station talking to one simulated airframe (sysid 1) through the wire."""

    def __init__(self, sim: SimulatedAirframe) -> None:
        self.sim = sim
        self.mav = mav.MAVLink(None, srcSystem=255, srcComponent=191)
        self.t_s = 0.0

    def send(self, name: str, *args: Any) -> list[Any]:
        msg = getattr(self.mav, f"{name}_encode")(*args)
        (parsed,) = self.sim._parser.parse_buffer(bytes(msg.pack(self.mav)))
        return self.sim.answer(parsed, self.t_s, self.t_s)

    def command(self, command: int, *params: float) -> tuple[int, list[Any]]:
        full = (*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)[:7]
        ack, *rest = self.send("command_long", 1, 1, command, 0, *full)
        assert ack.get_type() == "COMMAND_ACK"
        assert ack.command == command
        assert (ack.target_system, ack.target_component) == (255, 191)
        return int(ack.result), rest

    def upload(self, items: list[tuple[int, int, tuple[float, ...], float, float, float]]) -> None:
        replies = self.send("mission_count", 1, 1, len(items), 0)
        for seq, (command, frame, params, lat, lon, alt) in enumerate(items):
            assert replies[0].get_type() == "MISSION_REQUEST_INT"
            replies = self.send(
                "mission_item_int", 1, 1, seq, frame, command, 0, 1, *params,
                round(lat * 1e7), round(lon * 1e7), alt, 0,
            )  # fmt: skip
        assert (replies[0].get_type(), replies[0].type) == ("MISSION_ACK", 0)

    def fly(self, seconds: float, step_s: float = 0.1) -> list[Any]:
        """Step sim time; every message the airframe sends meanwhile."""
        out = []
        end = self.t_s + seconds
        while self.t_s < end - 1e-9:
            self.t_s += step_s
            out.extend(self.sim.messages_at(self.t_s))
        return out


def of(messages: list[Any], name: str) -> list[Any]:
    return [m for m in messages if m.get_type() == name]


def heartbeat(gcs: Gcs) -> Any:
    return of(gcs.fly(1.0), "HEARTBEAT")[-1]


def to_point(lat_deg: float, lon_deg: float, point: tuple[float, float] = POINT) -> float:
    return float(distance_bearing(lat_deg, lon_deg, *point)[0])


def observe_mission(
    alt: float = 320.0,
) -> list[tuple[int, int, tuple[float, ...], float, float, float]]:
    """A waypoint at POINT, then 30 s on a 200 m circle round it (what an order uploads)."""
    return [
        (16, 0, (0.0, 0.0, 0.0, 0.0), *POINT, alt),
        (19, 0, (30.0, 0.0, 200.0, 0.0), *POINT, alt),
    ]


class TestModes:
    """HEARTBEAT and the answers to mode commands, per autopilot."""

    def test_heartbeat_names_the_autopilot_and_its_mode(self) -> None:
        px4, apm = Gcs(SimulatedAirframe(1, autopilot="px4")), Gcs(SimulatedAirframe(1))
        hb = heartbeat(px4)
        assert (hb.autopilot, hb.custom_mode) == (mav.MAV_AUTOPILOT_PX4, PX4_LOITER)
        hb = heartbeat(apm)
        assert (hb.autopilot, hb.custom_mode) == (mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 15)
        assert px4.command(176, 1, 4, 5) == (mav.MAV_RESULT_ACCEPTED, [])
        assert heartbeat(px4).custom_mode == PX4_RTL
        assert apm.command(176, 1, 11) == (mav.MAV_RESULT_ACCEPTED, [])
        assert heartbeat(apm).custom_mode == 11
        assert heartbeat(apm).base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED

    @pytest.mark.parametrize(
        ("autopilot", "params", "result"),
        [
            ("px4", (1, 4, 4), mav.MAV_RESULT_DENIED),  # AUTO.MISSION with no mission
            ("px4", (1, 4, 3), mav.MAV_RESULT_ACCEPTED),  # AUTO.LOITER
            ("px4", (1, 1, 0), mav.MAV_RESULT_DENIED),  # MANUAL: no pilot's sticks here
            ("px4", (1, 4, 6), mav.MAV_RESULT_DENIED),  # AUTO.LAND: not flown
            ("px4", (0, 4, 4), mav.MAV_RESULT_UNSUPPORTED),  # no custom mode flag
            ("px4", (math.nan, 4, 4), mav.MAV_RESULT_UNSUPPORTED),
            ("ardupilot", (1, 10), mav.MAV_RESULT_FAILED),  # AUTO with no mission
            ("ardupilot", (1, 12), mav.MAV_RESULT_ACCEPTED),  # LOITER
            ("ardupilot", (1, 1), mav.MAV_RESULT_ACCEPTED),  # CIRCLE
            ("ardupilot", (1, 5), mav.MAV_RESULT_FAILED),  # FBWA: manual
            ("ardupilot", (1, 19), mav.MAV_RESULT_FAILED),  # QLOITER: VTOL
            ("ardupilot", (1, 1e30), mav.MAV_RESULT_FAILED),
            ("ardupilot", (0, 11), mav.MAV_RESULT_UNSUPPORTED),
        ],
    )
    def test_do_set_mode_is_answered_as_the_autopilot_would(
        self, autopilot: Any, params: tuple[float, ...], result: int
    ) -> None:
        gcs = Gcs(SimulatedAirframe(1, autopilot=autopilot))
        assert gcs.command(176, *params)[0] == result

    def test_set_mode_is_acknowledged_as_each_autopilot_does(self) -> None:
        apm = Gcs(SimulatedAirframe(1))
        (ack,) = apm.send("set_mode", 1, 1, 11)
        assert (ack.command, ack.result) == (mav.MAVLINK_MSG_ID_SET_MODE, 0)
        px4 = Gcs(SimulatedAirframe(1, autopilot="px4"))
        (ack,) = px4.send("set_mode", 1, 1, PX4_RTL)
        assert (ack.command, ack.result) == (176, 0)
        assert heartbeat(px4).custom_mode == PX4_RTL

    @pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
    def test_other_commands(self, autopilot: Any) -> None:
        gcs = Gcs(SimulatedAirframe(1, autopilot=autopilot))
        refusal = mav.MAV_RESULT_DENIED if autopilot == "px4" else mav.MAV_RESULT_FAILED
        assert gcs.command(400, 1)[0] == mav.MAV_RESULT_ACCEPTED  # armed already
        assert gcs.command(400, 0)[0] == refusal  # no disarming in the air
        assert gcs.command(300, 0, 0)[0] == refusal  # MISSION_START, no mission
        for effector in sorted(EFFECTOR_COMMANDS):
            assert gcs.command(effector, 1, 1900)[0] == mav.MAV_RESULT_UNSUPPORTED
        assert gcs.command(31010)[0] == mav.MAV_RESULT_UNSUPPORTED
        result, (home,) = gcs.command(512, 242)
        assert (result, home.get_type()) == (0, "HOME_POSITION")
        assert (home.latitude, home.longitude) == (658_252_000, 216_886_000)
        assert gcs.command(178, 0, 30)[0] == mav.MAV_RESULT_ACCEPTED
        assert gcs.command(178, 0, 500)[0] == refusal
        assert gcs.send("command_long", 2, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0) == []  # not ours


@pytest.mark.parametrize(
    ("autopilot", "fleet", "vehicle"),
    [
        ("px4", "px4", "plane"),
        ("ardupilot", "ardupilot", "plane"),
        ("arducopter", "ardupilot", "copter"),
        ("px4", "mavlink", "plane"),
        ("arducopter", "mavlink", "plane"),
    ],
)
def test_the_fleets_mode_commands_are_what_each_simulated_autopilot_takes(
    autopilot: Any, fleet: Any, vehicle: Any
) -> None:
    """The gateway's side (``gateway.fleet.missionitems``) against the simulated autopilots:
    its start puts each in mission mode, its return sends each home."""
    from gateway.fleet.missionitems import return_command, start_command

    sim = SimulatedAirframe(1, autopilot=autopilot)
    gcs = Gcs(sim)
    gcs.upload(observe_mission())
    command, params = start_command(fleet, 2, vehicle)
    assert gcs.command(command, *params)[0] == mav.MAV_RESULT_ACCEPTED
    assert sim.autopilot.mode == "mission"
    command, params = return_command(fleet, vehicle)
    assert gcs.command(command, *params)[0] == mav.MAV_RESULT_ACCEPTED
    assert sim.autopilot.mode == "rtl"


def test_arducopter_says_it_is_a_quadrotor_and_holds_at_the_mission_end() -> None:
    sim = SimulatedAirframe(1, autopilot="arducopter")
    gcs = Gcs(sim)
    hb = heartbeat(gcs)
    assert (hb.type, hb.autopilot, hb.custom_mode) == (mav.MAV_TYPE_QUADROTOR, 3, 4)
    assert gcs.command(176, 1, 10)[0] == mav.MAV_RESULT_FAILED  # 10 is no copter mode
    gcs.upload(observe_mission())
    assert gcs.command(176, 1, 3)[0] == mav.MAV_RESULT_ACCEPTED  # AUTO
    out = gcs.fly(240.0)
    assert [m.seq for m in of(out, "MISSION_ITEM_REACHED")] == [0, 1]
    assert of(out, "HEARTBEAT")[-1].custom_mode == 3  # still AUTO, holding
    assert sim.autopilot_summary() == (
        "autopilot arducopter: missions accepted 1, refused 0; commands answered 2, accepted 1;"
        " mode mission, item 1 of 2, complete"
    )
    assert SimulatedAirframe(2).autopilot_summary() is None


class TestFlying:
    """The mission flown: items in order, reached where they are, telemetry following."""

    @pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
    def test_an_observation_mission_is_flown_to_the_point_and_round_it(
        self, autopilot: Any
    ) -> None:
        sim = SimulatedAirframe(1, autopilot=autopilot, position_history=10_000)
        gcs = Gcs(sim)
        gcs.fly(5.0)
        gcs.upload(observe_mission())
        start = {"px4": (1, 4, 4), "ardupilot": (1, 10)}[autopilot]
        assert gcs.command(176, *start)[0] == mav.MAV_RESULT_ACCEPTED
        sent = len(sim.sent_positions)
        out = gcs.fly(240.0)
        reached = [(m.seq, i) for i, m in enumerate(out) if m.get_type() == "MISSION_ITEM_REACHED"]
        assert [seq for seq, _ in reached] == [0, 1]
        positions = list(sim.sent_positions)[sent:]
        d = [to_point(p.lat_e7 / 1e7, p.lon_e7 / 1e7) for p in positions]
        arrived = next(i for i, x in enumerate(d) if x <= 80.0)
        assert min(d) < 80.0
        # After the waypoint: onto the 200 m circle, where 30 s are spent, never wider.
        done = arrived + next(i for i, x in enumerate(d[arrived:]) if abs(x - 200) < 25)
        assert all(x <= 240.0 for x in d[arrived : done + 250])
        assert all(abs(x - 200.0) <= 25.0 for x in d[done + 50 : done + 250])
        assert positions[done + 250].alt_mm == 320_000  # climbed at most 4 m/s from 250 m
        currents = [m for m in out if m.get_type() == "MISSION_CURRENT"]
        assert currents[-1].mission_state == mav.MISSION_STATE_COMPLETE
        hb = of(out, "HEARTBEAT")[-1]
        if autopilot == "px4":  # PX4 stays in mission mode, circling the last item
            assert hb.custom_mode == PX4_MISSION
            assert abs(d[-1] - 200.0) <= 25.0
        else:  # ArduPlane: "Mission complete, changing mode to RTL", and home it goes
            assert hb.custom_mode == 11
            home = [to_point(p.lat_e7 / 1e7, p.lon_e7 / 1e7, CENTRE) for p in positions]
            assert home[-1] < home[reached[-1][1] // 20]

    def test_turns_speed_relative_altitude_and_return(self) -> None:
        sim = SimulatedAirframe(1, autopilot="px4", position_history=20_000)
        gcs = Gcs(sim)
        gcs.upload(
            [
                (178, 2, (0.0, 30.0, -1.0, 0.0), 0.0, 0.0, 0.0),  # DO_CHANGE_SPEED 30 m/s
                (18, 3, (2.0, 0.0, -150.0, 0.0), *POINT, 120.0),  # 2 turns, ccw, 120 m AGL
                (20, 0, (0.0, 0.0, 0.0, 0.0), 0.0, 0.0, 0.0),  # home
            ]
        )
        assert gcs.command(300, 0, 2)[0] == mav.MAV_RESULT_ACCEPTED  # MISSION_START
        out = gcs.fly(400.0)
        assert [m.seq for m in of(out, "MISSION_ITEM_REACHED")] == [0, 1, 2]
        hud = of(out, "VFR_HUD")[-1]
        assert hud.airspeed == pytest.approx(30.0)
        assert hud.alt == pytest.approx(250.0)  # RTL at the orbit's altitude
        gpi = of(out, "GLOBAL_POSITION_INT")
        on_circle = [m for m in gpi if abs(m.alt - 270_000) < 500]  # home 150 m + 120 m
        assert on_circle
        last = gpi[-1]
        assert to_point(last.lat / 1e7, last.lon / 1e7, CENTRE) < 300.0

    def test_the_camera_looks_at_the_point_flown_to(self) -> None:
        gcs = Gcs(SimulatedAirframe(1, SimProfile(camera_hz=1.0), autopilot="px4"))
        before = of(gcs.fly(2.0), "CAMERA_FOV_STATUS")[-1]
        assert (before.lat_image, before.lon_image) == (658_252_000, 216_886_000)  # the centre
        gcs.upload(observe_mission())
        gcs.command(176, 1, 4, 4)
        fov = of(gcs.fly(10.0), "CAMERA_FOV_STATUS")[-1]
        assert (fov.lat_image, fov.lon_image) == (round(POINT[0] * 1e7), round(POINT[1] * 1e7))

    def test_a_new_mission_is_flown_from_its_first_item_and_clear_all_holds(self) -> None:
        sim = SimulatedAirframe(1)
        gcs = Gcs(sim)
        gcs.upload(observe_mission())
        gcs.command(176, 1, 10)
        gcs.fly(20.0)
        gcs.upload(observe_mission(400.0))
        assert sim.autopilot.current == 0
        assert heartbeat(gcs).custom_mode == 10
        (ack,) = gcs.send("mission_clear_all", 1, 1, 0)
        assert ack.type == 0
        assert heartbeat(gcs).custom_mode == 12  # LOITER where it is
        assert not of(gcs.fly(2.0), "MISSION_ITEM_REACHED")


SCENARIO = """
name: far
duration_s: 600
airframes:
  - id: F26E-001
    sysid: 1
    orbit: {centre_lat_deg: 65.8252, centre_lon_deg: 21.6886, radius_m: 400,
            alt_msl_m: 250, speed_mps: 22}
    sensors:
      - {sensor: eo, range_m: 1500, confidence: 0.8, sigma_h_m: 0, rate_hz: 1}
targets:
  - {id: T1, class: tank, path: [{lat_deg: 65.8500, lon_deg: 21.7000, alt_msl_m: 150}]}
"""


def test_detections_are_looked_for_from_where_the_airframe_flies() -> None:
    """A tank 2.9 km from the orbit is out of the camera's 1.5 km; flown to, it is seen."""
    scenario = load_scenario_text(SCENARIO)
    sim = SimulatedAirframe(1, scenario.airframes[0].profile())
    feed = DetectionFeed(scenario, scenario.airframes[0], 600.0, sim.position_at)
    sim.feed = feed
    gcs = Gcs(sim)
    assert not of(gcs.fly(20.0), "FISCHER_DETECTION")
    gcs.upload([(16, 0, (0.0, 0.0, 0.0, 0.0), 65.8500, 21.7000, 250.0)])
    gcs.command(176, 1, 10)
    seen = of(gcs.fly(150.0), "FISCHER_DETECTION")
    assert seen
    assert {(d.lat, d.lon) for d in seen} == {(658_500_000, 217_000_000)}
    assert [d.detection_id for d in seen] == list(range(1, len(seen) + 1))


@settings(max_examples=200, deadline=None)
@given(
    st.sampled_from(["px4", "ardupilot"]),
    st.lists(
        st.tuples(
            st.one_of(
                st.sampled_from([176, 300, 20, 17, 224, 178, 400, 512, *EFFECTOR_COMMANDS]),
                st.integers(0, 65535),
            ),
            st.lists(st.floats(width=32), min_size=7, max_size=7),
        ),
        max_size=12,
    ),
)
def test_any_command_gets_one_honest_answer(autopilot: Any, commands: list[Any]) -> None:
    """Whatever is commanded: exactly one COMMAND_ACK with a result the autopilot gives,
    UNSUPPORTED for every effector, and the airframe flies on, armed, in finite numbers."""
    gcs = Gcs(SimulatedAirframe(1, autopilot=autopilot))
    gcs.upload(observe_mission())
    allowed = {0, 3, 2 if autopilot == "px4" else 4}
    for command, params in commands:
        replies = gcs.send("command_long", 1, 1, command, 0, *params)
        acks = of(replies, "COMMAND_ACK")
        assert len(acks) == 1
        assert acks[0].result in allowed
        if command in EFFECTOR_COMMANDS:
            assert acks[0].result == mav.MAV_RESULT_UNSUPPORTED
        gcs.fly(0.5)
    out = gcs.fly(3.0)
    assert of(out, "HEARTBEAT")[-1].base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    for m in of(out, "GLOBAL_POSITION_INT"):
        assert abs(m.lat) <= 900_000_000
        assert 200_000 <= m.alt <= 400_000


@pytest.mark.anyio
async def test_over_udp_a_silent_station_is_asked_again_then_cancelled() -> None:
    """The mission timer runs beside the flight: re-requests on the wire, then the ACK."""
    sim = SimulatedAirframe(1, autopilot="px4")
    sim.missions.item_timeout_s = 0.05
    sim.missions.item_retries = 3
    gcs = mav.MAVLink(None, srcSystem=255, srcComponent=191)
    parser = mav.MAVLink(None)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock, anyio.fail_after(20):
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        port = sock.getsockname()[1]
        got: list[Any] = []
        async with anyio.create_task_group() as tg:
            await tg.start(sim.run_udp, "127.0.0.1", port)
            while not got:  # the airframe's first datagram names its address
                await anyio.wait_readable(sock)
                _, peer = sock.recvfrom(4096)
                sock.sendto(bytes(gcs.mission_count_encode(1, 1, 2, 0).pack(gcs)), peer)
                got.append(peer)
            mission: list[Any] = []
            while not any(m.get_type() == "MISSION_ACK" for m in mission):
                await anyio.wait_readable(sock)
                data, _ = sock.recvfrom(4096)
                for m in parser.parse_buffer(data) or []:
                    if m.get_type().startswith("MISSION_") and m.get_type() != "MISSION_CURRENT":
                        mission.append(m)
            tg.cancel_scope.cancel()
    assert [
        (m.get_type(), getattr(m, "seq", m.type if m.get_type() == "MISSION_ACK" else None))
        for m in mission
    ] == [("MISSION_REQUEST_INT", 0)] * 4 + [("MISSION_ACK", mav.MAV_MISSION_OPERATION_CANCELLED)]
