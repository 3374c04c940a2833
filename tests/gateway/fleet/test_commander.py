"""The fleet's airframe commander as the assembly builds it for a tasking processor."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from types import SimpleNamespace
from typing import Any

import pytest

from gateway.app import Gateway
from gateway.config import Config
from gateway.domain.mission import Loiter, MissionStep, ModeCommands, Outcome, Waypoint
from gateway.fleet.commander import FleetCommander
from gateway.fleet.missionitems import MAV_CMD_NAV_LOITER_TIME, MAV_CMD_NAV_WAYPOINT, MissionItem
from gateway.flow.tasking import AirframeCommander

built: list[Gateway] = []


@pytest.fixture(autouse=True)
def closed() -> Iterator[None]:
    """Gateways built here are never run: close what running would have closed."""
    yield
    while built:
        gw = built.pop()
        for runner in gw.processors.values():
            runner.close()
        gw.spool.close()


def gateway(processors: list[dict[str, object]]) -> Gateway:
    config = Config.model_validate(
        {
            "health": {"enabled": False},
            "airframes": [
                {
                    "id": "F26E-001",
                    "sysid": 1,
                    "links": [{"uri": "udp://127.0.0.1:0", "security": "unsecured"}],
                }
            ],
            "processors": processors,
        }
    )
    built.append(Gateway(config))
    return built[-1]


def test_only_a_node_with_a_tasking_processor_gets_a_commander() -> None:
    assert gateway([]).fleet.commander is None
    assert gateway([{"name": "fusion", "type": "fusion"}]).fleet.commander is None
    tasked = gateway([{"name": "orders", "type": "orders"}])
    assert isinstance(tasked.fleet.commander, AirframeCommander)
    assert tasked.fleet.commander.is_known("F26E-001")
    assert not tasked.fleet.commander.is_known("F26E-404")
    assert not tasked.fleet.commander.is_linked("F26E-001")  # nothing heard from it yet


@pytest.mark.anyio
async def test_an_airframe_without_a_link_is_an_outcome_not_an_error() -> None:
    commander = gateway([{"name": "orders", "type": "orders"}]).fleet.commander
    assert commander is not None
    step = Waypoint(65.85, 21.1, 500.0)
    uploaded = await commander.upload_mission("F26E-001", [step], timeout_s=0.1, retries=0)
    assert (uploaded.ok, uploaded.attempts) == (False, 0)
    assert uploaded.detail.startswith("not sent: ")
    commanded = await commander.start_mission("F26E-001", 1, "px4", timeout_s=0.1, retries=0)
    assert not commanded.ok
    assert commanded.detail.startswith("command 176 not sent: ")


class _Recording(FleetCommander):
    """The fleet's commander with the MAVLink it would send recorded instead."""

    def __init__(self) -> None:
        super().__init__({}, lambda _airframe: True)
        self.sent: list[tuple[str, object]] = []

    async def command(
        self,
        airframe: str,
        command: int,
        params: Sequence[float],
        *,
        timeout_s: float,
        retries: int,
    ) -> Outcome:
        self.sent.append(("command", (command, tuple(params))))
        return Outcome(True, "MAV_RESULT_ACCEPTED")

    async def upload_items(
        self, airframe: str, items: Sequence[MissionItem], *, timeout_s: float, retries: int
    ) -> Outcome:
        self.sent.append(("items", list(items)))
        return Outcome(True, "MAV_MISSION_ACCEPTED")


@pytest.mark.parametrize(
    ("mode_commands", "start", "home"),
    [
        ("px4", (176, (1.0, 4.0, 4.0)), (176, (1.0, 4.0, 5.0))),
        ("mavlink", (300, (0.0, 1.0)), (20, ())),
    ],
)
@pytest.mark.anyio
async def test_the_fleet_picks_the_mavlink_of_an_intent(
    mode_commands: ModeCommands, start: object, home: object
) -> None:
    """Orders speak in intents; the fleet says them in MAVLink (PX4 modes or plain commands)."""
    commander = _Recording()
    steps: list[MissionStep] = [
        Waypoint(65.85, 21.1, 500.0),
        Loiter(65.85, 21.1, 500.0, 600.0, 300.0),
    ]
    for outcome in (
        await commander.upload_mission("F26E-001", steps, timeout_s=1.0, retries=0),
        await commander.start_mission("F26E-001", 2, mode_commands, timeout_s=1.0, retries=0),
        await commander.return_to_base("F26E-001", mode_commands, timeout_s=1.0, retries=0),
    ):
        assert outcome.ok
    assert commander.sent == [
        (
            "items",
            [
                MissionItem(MAV_CMD_NAV_WAYPOINT, 65.85, 21.1, 500.0),
                MissionItem(MAV_CMD_NAV_LOITER_TIME, 65.85, 21.1, 500.0, (600.0, 0.0, 300.0, 0.0)),
            ],
        ),
        ("command", start),
        ("command", home),
    ]


def _heartbeat(autopilot: int, mav_type: int) -> object:
    from pymavlink.dialects.v20 import ardupilotmega as apm

    sender = apm.MAVLink(None, srcSystem=1, srcComponent=1)
    msg = sender.heartbeat_encode(mav_type, autopilot, 0, 0, 4)
    (parsed,) = apm.MAVLink(None).parse_buffer(bytes(msg.pack(sender)))
    return parsed


class _Heard(FleetCommander):
    """The assembly's commander for one airframe (config ``extra``), commands recorded."""

    def __init__(self, extra: dict[str, object]) -> None:
        gw = gateway_with([{"name": "orders", "type": "orders"}], extra)
        assert gw.fleet.commander is not None
        super().__init__(gw.fleet.sessions, lambda _airframe: True)
        self.session = gw.fleet.sessions["F26E-001"]
        self.sent: list[tuple[int, tuple[float, ...]]] = []

    def hear(self, autopilot: int, mav_type: int) -> None:
        self.session.dispatch("fleet", "HEARTBEAT", _heartbeat(autopilot, mav_type))

    async def command(
        self,
        airframe: str,
        command: int,
        params: Sequence[float],
        *,
        timeout_s: float,
        retries: int,
    ) -> Outcome:
        self.sent.append((command, tuple(params)))
        return Outcome(True, "MAV_RESULT_ACCEPTED")

    async def intents(self, fallback: ModeCommands) -> list[tuple[int, tuple[float, ...]]]:
        self.sent.clear()
        await self.start_mission("F26E-001", 3, fallback, timeout_s=1.0, retries=0)
        await self.return_to_base("F26E-001", fallback, timeout_s=1.0, retries=0)
        return list(self.sent)


def gateway_with(processors: list[dict[str, object]], extra: dict[str, object]) -> Gateway:
    config = Config.model_validate(
        {
            "health": {"enabled": False},
            "airframes": [
                {
                    "id": "F26E-001",
                    "sysid": 1,
                    "links": [{"uri": "udp://127.0.0.1:0", "security": "unsecured"}],
                    **extra,
                }
            ],
            "processors": processors,
        }
    )
    built.append(Gateway(config))
    return built[-1]


PX4 = [(176, (1.0, 4.0, 4.0)), (176, (1.0, 4.0, 5.0))]
PLANE = [(176, (1.0, 10.0, 0.0)), (176, (1.0, 11.0, 0.0))]
COPTER = [(176, (1.0, 3.0, 0.0)), (176, (1.0, 6.0, 0.0))]
PLAIN = [(300, (0.0, 2.0)), (20, ())]


@pytest.mark.anyio
async def test_the_autopilot_comes_from_the_config_then_the_heartbeat_then_the_caller() -> None:
    """``autopilot`` in the config wins; else the HEARTBEAT's autopilot (ArduCopter's
    numbers for a multirotor); else what the orders processor asks (``mode_commands``)."""
    heard = _Heard({})
    assert await heard.intents("px4") == PX4
    assert await heard.intents("mavlink") == PLAIN
    heard.hear(3, 1)  # ArduPilot, fixed wing: ArduPlane
    assert await heard.intents("px4") == PLANE
    heard.hear(3, 2)  # ArduPilot, quadrotor: ArduCopter
    assert await heard.intents("mavlink") == COPTER
    heard.hear(8, 6)  # a ground station's heartbeat under the same sysid: not the autopilot
    assert await heard.intents("mavlink") == COPTER
    heard.hear(12, 1)  # PX4
    assert await heard.intents("mavlink") == PX4
    assert heard.autopilot("F26E-001", "mavlink") == ("px4", "plane")
    configured = _Heard({"autopilot": "mavlink"})
    configured.hear(12, 1)
    assert await configured.intents("px4") == PLAIN
    plane = _Heard({"autopilot": "ardupilot"})
    assert await plane.intents("px4") == PLANE


def test_an_airframe_is_tasked_only_once_its_flight_controller_was_heard() -> None:
    """Its position and battery state can come before its first HEARTBEAT (after a restart
    of the gateway, or when the link comes up): until the HEARTBEAT the autopilot, hence the
    mode numbers, are unknown, so the airframe is not yet linked for tasking; a ground
    station's HEARTBEAT under its sysid does not count."""
    heard = _Heard({})
    assert not heard.is_linked("F26E-001")
    heard.hear(8, 6)  # MAV_AUTOPILOT_INVALID: a ground station
    assert not heard.is_linked("F26E-001")
    heard.hear(3, 1)  # ArduPlane
    assert heard.is_linked("F26E-001")
    assert heard.autopilot("F26E-001", "px4") == ("ardupilot", "plane")
    # Configured ArduPilot still needs the HEARTBEAT (plane or copter numbers); PX4's and
    # plain MAVLink's numbers need neither.
    assert not _Heard({"autopilot": "ardupilot"}).is_linked("F26E-001")
    assert _Heard({"autopilot": "px4"}).is_linked("F26E-001")
    assert _Heard({"autopilot": "mavlink"}).is_linked("F26E-001")


def test_mode_commands_is_the_older_name_of_autopilot() -> None:
    from gateway.configfile import load_model_text
    from gateway.errors import ConfigError

    assert (
        gateway_with([], {"mode_commands": "mavlink"}).fleet.sessions["F26E-001"].config.autopilot
        == "mavlink"
    )
    text = """
airframes:
  - {id: F26E-001, sysid: 1, links: [{uri: 'udp://127.0.0.1:0', security: unsecured}],
     autopilot: ardupilot, mode_commands: px4}
  - {id: F26E-002, sysid: 2, links: [{uri: 'udp://127.0.0.1:1', security: unsecured}],
     autopilot: inav}
"""
    with pytest.raises(ConfigError) as caught:
        load_model_text(text, "node.yaml", Config)
    messages = {issue.key_path: issue.message for issue in caught.value.issues}
    assert "disagree" in messages["airframes[0]"]
    assert "px4" in messages["airframes[1].autopilot"]


class _Airframe:
    """A session whose airframe holds ``items`` and answers a download as told."""

    def __init__(self, items: Sequence[MissionItem], *, silent: set[int] | None = None) -> None:
        self.id = "F26E-001"
        self.config = SimpleNamespace(sysid=1, autopilot=None)
        self.items = items
        self.silent = silent or set()  # item seqs whose requests go unanswered
        self.handlers: dict[str, list[Any]] = {}
        self.sent: list[tuple[str, tuple[object, ...]]] = []

    def on(self, message: str, handler: Any) -> None:
        self.handlers.setdefault(message, []).append(handler)

    def pack(self, name: str, *args: object) -> tuple[str, tuple[object, ...]]:
        return name, args

    def _answer(self, name: str, **fields: object) -> None:
        msg = SimpleNamespace(target_system=255, target_component=0, mission_type=0, **fields)
        msg.get_type = lambda: name
        for handler in self.handlers.get(name, []):
            handler(self, name, msg)

    async def send(self, frame: tuple[str, tuple[object, ...]]) -> None:
        self.sent.append(frame)
        name, args = frame
        if name == "mission_request_list":
            self._answer("MISSION_COUNT", count=len(self.items))
        elif name == "mission_request_int" and args[2] not in self.silent:
            seq = int(str(args[2]))
            item = self.items[seq]
            self._answer(
                "MISSION_ITEM_INT", seq=seq, frame=item.frame, command=item.command,
                param1=item.params[0], param3=item.params[2],
                x=round(item.lat_deg * 1e7), y=round(item.lon_deg * 1e7), z=item.alt_msl_m,
            )  # fmt: skip


def _reading(airframe: _Airframe) -> FleetCommander:
    return FleetCommander({airframe.id: airframe}, lambda _a: True)  # type: ignore[dict-item]


@pytest.mark.anyio
async def test_a_mission_is_read_back_item_by_item_and_acknowledged() -> None:
    held = [
        MissionItem(MAV_CMD_NAV_WAYPOINT, 65.85, 21.1, 500.0),
        MissionItem(MAV_CMD_NAV_LOITER_TIME, 65.85, 21.1, 500.0, (60.0, 0.0, 300.0, 0.0)),
    ]
    airframe = _Airframe(held)
    got, steps = await _reading(airframe).download_mission(airframe.id, timeout_s=1, retries=1)
    assert got.ok
    assert steps == (Waypoint(65.85, 21.1, 500.0), Loiter(65.85, 21.1, 500.0, 60.0, 300.0))
    assert [name for name, _ in airframe.sent] == [
        "mission_request_list", "mission_request_int", "mission_request_int", "mission_ack",
    ]  # fmt: skip


@pytest.mark.anyio
async def test_a_mission_of_other_commands_is_none_of_ours_and_says_which() -> None:
    airframe = _Airframe([MissionItem(22, 65.85, 21.1, 500.0)])  # NAV_TAKEOFF
    got, steps = await _reading(airframe).download_mission(airframe.id, timeout_s=1, retries=0)
    assert not got.ok
    assert got.detail == "item 0 is command 22 in frame 0"
    assert steps == ()


@pytest.mark.anyio
async def test_an_item_never_answered_ends_the_read_back_after_its_retries() -> None:
    airframe = _Airframe([MissionItem(MAV_CMD_NAV_WAYPOINT, 65.85, 21.1, 500.0)], silent={0})
    got, _ = await _reading(airframe).download_mission(airframe.id, timeout_s=0.01, retries=2)
    assert not got.ok
    assert got.detail == "mission download: 0 of 1 items after 4 requests"
