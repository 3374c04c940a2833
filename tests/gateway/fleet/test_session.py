"""The airframe session's outbound path: a command correlated with its COMMAND_ACK, over UDP.

A real gateway (unsecured UDP link on loopback) and the simulator, which answers COMMAND_LONG
with COMMAND_ACK, or, told not to, plays a lost uplink.
"""

from __future__ import annotations

from functools import partial

import anyio
import pytest
from structlog.testing import capture_logs

from gateway.app import Gateway
from gateway.config import Config
from gateway.sim.airframe import SimulatedAirframe
from gateway.testing import MemorySink, eventually

MAV_CMD_COMPONENT_ARM_DISARM = 400  # any command the simulator acknowledges will do
MAV_CMD_DO_SET_MODE = 176


def gateway() -> Gateway:
    config = Config.model_validate(
        {
            "gateway": {"shutdown_deadline_s": 1},
            "health": {"enabled": False},
            "airframes": [
                {
                    "id": "F26E-001",
                    "sysid": 1,
                    "links": [{"uri": "udp://127.0.0.1:0", "security": "unsecured"}],
                }
            ],
            "sinks": [{"name": "mem", "type": "memory"}],
            "routes": [{"sinks": ["mem"]}],
        }
    )
    return Gateway(config, sinks={"mem": MemorySink("mem")})


@pytest.mark.anyio
async def test_a_command_is_correlated_with_its_ack_and_a_lost_one_is_retried_then_reported() -> (
    None
):
    gw = gateway()
    sim = SimulatedAirframe(1)
    with anyio.fail_after(20):
        async with anyio.create_task_group() as tg:
            await tg.start(gw.run)
            port = next(iter(gw.fleet.links.values())).local_port  # type: ignore[attr-defined]
            await tg.start(partial(sim.run_udp, "127.0.0.1", port))
            await eventually(lambda: gw.fleet.ingest.active_link("F26E-001") is not None)
            session = gw.fleet.sessions["F26E-001"]

            done = await session.command_long(MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
            assert done.is_accepted
            assert done.result_name == "MAV_RESULT_ACCEPTED"
            assert done.attempts == 1
            assert done.latency_s is not None
            assert 0 < done.latency_s < 1.0
            assert sim.commands == [(MAV_CMD_COMPONENT_ARM_DISARM, 0)]

            sim.ack_commands = False
            with capture_logs() as logs:
                lost = await session.command_long(MAV_CMD_DO_SET_MODE, 1, timeout_s=0.2, retries=2)
            assert lost.result is None
            assert lost.result_name == "TIMEOUT"
            assert lost.attempts == 3
            # Each retry says it is one (MAVLink's confirmation field counts them).
            assert sim.commands[1:] == [(MAV_CMD_DO_SET_MODE, n) for n in range(3)]
            assert [e["event"] for e in logs] == ["command_timed_out"]
            status = gw.status()["airframes"][0]
            assert status["commands_sent"] == 4
            assert status["commands_timed_out"] == 1
            assert status["last_command"]["result"] == "TIMEOUT"
            gw.shutdown()
            tg.cancel_scope.cancel()


class _Ack:
    """A COMMAND_ACK as pymavlink decodes it."""

    def __init__(self, command: int, result: int, target: tuple[int, int]) -> None:
        self.command, self.result = command, result
        self.target_system, self.target_component = target


@pytest.mark.anyio
async def test_in_progress_stops_resending_and_a_foreign_ack_is_not_ours() -> None:
    from gateway.fleet.session import GATEWAY_COMPID, GATEWAY_SYSID

    gw = gateway()
    session = gw.fleet.sessions["F26E-001"]
    sent: list[bytes] = []

    async def transmit(_airframe: str, frames: bytes) -> None:
        sent.append(frames)

    session.set_transmit(transmit)
    ours = (GATEWAY_SYSID, GATEWAY_COMPID)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:

            async def airframe() -> None:
                await eventually(lambda: len(sent) == 1)
                # QGroundControl's ACK for the same command id: addressed to 255/190.
                session.on_command_ack(session, "l", _Ack(241, 4, (255, 190)))
                session.on_command_ack(session, "l", _Ack(241, 5, ours))  # IN_PROGRESS
                await anyio.sleep(0.5)  # longer than the timeout: no resend may follow
                session.on_command_ack(session, "l", _Ack(241, 0, ours))

            tg.start_soon(airframe)
            done = await session.command_long(241, 1.0, timeout_s=0.2, retries=3)
    assert len(sent) == 1
    assert done.is_accepted
    assert done.attempts == 1


class TestMessageHandlers:
    """``on`` adds a handler beside the others; it never silently replaces one."""

    def test_several_handlers_of_one_message_each_get_it_in_order(self) -> None:
        session = gateway().fleet.sessions["F26E-001"]
        seen: list[tuple[str, str, object]] = []
        session.on("SCALED_PRESSURE", lambda _s, label, m: seen.append(("first", label, m)))
        session.on("SCALED_PRESSURE", lambda _s, label, m: seen.append(("second", label, m)))
        msg = object()
        session.dispatch("l", "SCALED_PRESSURE", msg)  # type: ignore[arg-type]
        assert seen == [("first", "l", msg), ("second", "l", msg)]
        assert len(session.handlers("SCALED_PRESSURE")) == 2
        # What ingest and the commander register is there once each: nothing was replaced.
        assert len(session.handlers("HEARTBEAT")) == 1
        assert len(session.handlers("COMMAND_ACK")) == 1

    def test_registering_the_same_handler_twice_is_an_error(self) -> None:
        session = gateway().fleet.sessions["F26E-001"]

        def handler(_session: object, _label: str, _msg: object) -> None:
            pass

        session.on("FISCHER_HOP_EVENT", handler)
        with pytest.raises(ValueError, match="already handles FISCHER_HOP_EVENT"):
            session.on("FISCHER_HOP_EVENT", handler)
        assert session.handlers("FISCHER_HOP_EVENT").count(handler) == 1

    def test_a_failing_handler_keeps_the_message_from_no_other(self) -> None:
        session = gateway().fleet.sessions["F26E-001"]
        seen: list[str] = []

        def broken(_session: object, _label: str, _msg: object) -> None:
            raise KeyError("a bug in a handler")

        session.on("SCALED_PRESSURE", broken)
        session.on("SCALED_PRESSURE", lambda _s, _l, _m: seen.append("after"))
        with pytest.raises(KeyError, match="a bug in a handler"):
            session.dispatch("l", "SCALED_PRESSURE", object())  # type: ignore[arg-type]
        assert seen == ["after"]


class TestState:
    """The session's state is its own: changed through its methods, read through properties."""

    def test_a_peer_is_learned_once_and_forgotten_only_by_itself(self) -> None:
        from gateway.fleet.mavlink import dialect

        session = gateway().fleet.sessions["F26E-001"]
        (label,) = session.labels
        mav = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
        msg = mav.heartbeat_encode(1, 12, 0, 0, 4)  # a flight controller (PX4)
        buf = msg.pack(mav)
        trusted: list[object] = []
        for peer in (("127.0.0.1", 5), ("127.0.0.1", 5)):
            assert session.accept(label, peer, True, trusted.append, buf, "HEARTBEAT", msg, 1.0)
        assert trusted == [("127.0.0.1", 5)]  # told once, when it was new
        assert session.peer(label) == ("127.0.0.1", 5)
        assert session.health.autopilot_compid == 1
        # An unsigned frame the config lets through proves nothing: no peer is learned.
        session.accept(label, ("127.0.0.1", 7), False, trusted.append, buf, "HEARTBEAT", msg, 1.0)
        assert session.peer(label) == ("127.0.0.1", 5)
        session.forget_peer(label, ("127.0.0.1", 6))  # another connection closed
        assert session.peer(label) == ("127.0.0.1", 5)
        session.forget_peer(label, ("127.0.0.1", 5))
        assert session.peer(label) is None

    def test_fields_are_read_only(self) -> None:
        session = gateway().fleet.sessions["F26E-001"]
        with pytest.raises(AttributeError):
            session.commands_sent = 5  # type: ignore[misc]
        with pytest.raises(AttributeError):
            session.peers = {}  # type: ignore[attr-defined]
