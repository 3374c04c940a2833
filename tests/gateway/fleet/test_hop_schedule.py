"""The hop schedule in the gateway (gateway/fleet/hopschedule.py) against the simulated
airframe's radio (gateway/sim/radio.py) over real UDP on loopback: upload, answer, re-send
after a lost answer, refusal, a schedule lost by the airframe, and hop events in."""

from __future__ import annotations

import hashlib
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import anyio
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as apm

from gateway.app import Gateway
from gateway.config import SIGNED_ONLY_MSGIDS, Config, HopPlanConfig
from gateway.configfile import load_config_text
from gateway.contract import sample_events
from gateway.errors import ConfigError
from gateway.events import EventKind, HopEvent, HopReason
from gateway.fleet.hopdialect import (
    HOP_REASON_NAMES,
    HOP_RESULT_ACCEPTED,
    HOP_RESULT_UNSUPPORTED_DWELL,
    MAVLINK_MSG_ID_FISCHER_HOP_EVENT,
    MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE_ACK,
    FischerHopEvent,
    FischerHopSchedule,
    FischerHopScheduleAck,
)
from gateway.fleet.hopschedule import (
    PUBLISH_BURST,
    STATES,
    hop_schedule_message,
    schedule_id,
)
from gateway.sim.airframe import SimProfile, SimulatedAirframe
from gateway.sim.radio import SimRadio
from gateway.testing import MemorySink, eventually
from sinks.console import describe

HOP_REASONS = tuple(HOP_REASON_NAMES.values())
PLAN = {
    "frequencies_mhz": [2405.0, 2420.0, 2435.0, 5800.0],
    "bandwidth_mhz": 10.0,
    "dwell_us": 12.0,
    "ack_timeout_s": 0.3,
    "retry_max_s": 1.0,
}


def gateway_config(plan: dict[str, Any] | None = PLAN, signing_key: Path | None = None) -> Config:
    airframe: dict[str, Any] = {
        "id": "F26E-001",
        "sysid": 1,
        "links": [{"uri": "udp://127.0.0.1:0", "security": "unsecured"}],
    }
    if signing_key is not None:
        airframe["links"][0]["security"] = "signed"
        airframe["signing"] = {"key_file": str(signing_key)}
    if plan is not None:
        airframe["hop_plan"] = plan
    return Config.model_validate(
        {
            "health": {"enabled": False},
            "airframes": [airframe],
            "sinks": [{"name": "mem", "type": "memory"}],
            "routes": [{"sinks": ["mem"], "kinds": ["hop"]}],
        }
    )


def fast_profile() -> SimProfile:
    return SimProfile(position_hz=2.0, gps_hz=1.0, status_hz=1.0, hop_event_hz=10.0)


async def fly(gateway: Gateway, sim: SimulatedAirframe, until: Any, timeout_s: float = 15) -> None:
    """Run the gateway and the simulated airframe until ``until()`` holds."""
    with anyio.fail_after(timeout_s):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            port = next(iter(gateway.fleet.links.values())).local_port  # type: ignore[attr-defined]
            tg.start_soon(lambda: sim.run_udp("127.0.0.1", port, duration_s=None))
            await eventually(until)
            gateway.shutdown()
            await gateway.stopped.wait()
            tg.cancel_scope.cancel()


def hop_events(mem: MemorySink) -> list[HopEvent]:
    return [e for e in mem.events if isinstance(e, HopEvent)]


@pytest.mark.anyio
async def test_the_plan_is_accepted_and_hops_come_back_as_events() -> None:
    mem = MemorySink("mem")
    gateway = Gateway(gateway_config(), sinks={"mem": mem})
    sim = SimulatedAirframe(1, fast_profile())
    await fly(gateway, sim, lambda: len({e.reason for e in hop_events(mem)}) == 2)
    (upload,) = gateway.fleet.hops.status()
    sid = schedule_id(HopPlanConfig.model_validate(PLAN))
    assert upload == {
        "airframe": "F26E-001",
        "schedule_id": f"{sid:08x}",
        "state": "accepted",
        "sends": 1,
        "last_result": "accepted",
        "active_schedule_id": f"{sid:08x}",
    }
    assert sim.radio.schedules == [sid]
    assert sim.radio.active is not None
    assert list(sim.radio.active.frequencies[:4]) == [2405e6, 2420e6, 2435e6, 5800e6]
    assert (sim.radio.active.dwell, sim.radio.active.bandwidth) == (12_000, 10_000_000)
    events = hop_events(mem)
    assert all(e.schedule_id == sid and e.is_gateway_schedule for e in events)
    assert {e.frequency_hz for e in events} <= {2405e6, 2420e6, 2435e6, 5800e6}
    jammed = [e for e in events if e.reason is HopReason.JAMMED]
    assert jammed[0].interference_dbm == -27.0
    inst = gateway.instruments
    assert inst.hop_events.labels("F26E-001", "jammed").value == len(jammed)
    assert inst.hops.labels("F26E-001").value == max(e.hop_count for e in events)
    assert inst.hop_schedule_answers.labels("F26E-001", "accepted").value == 1
    assert 'fg_hop_schedule_state{airframe="F26E-001",state="accepted"} 1' in (
        inst.registry.render()
    )


@pytest.mark.anyio
async def test_on_a_signed_link_the_schedule_and_its_answer_go_signed(
    tmp_path: Path,
) -> None:
    key = hashlib.sha256(b"hop airframe 1 signing key").digest()
    (tmp_path / "s.key").write_bytes(key)
    (tmp_path / "s.key").chmod(0o600)
    mem = MemorySink("mem")
    gateway = Gateway(gateway_config(signing_key=tmp_path / "s.key"), sinks={"mem": mem})
    sim = SimulatedAirframe(1, fast_profile(), signing_key=key)
    await fly(gateway, sim, lambda: bool(hop_events(mem)))
    assert gateway.fleet.hops.status()[0]["state"] == "accepted"
    assert sim.radio.schedules == [gateway.fleet.hops.uploads["F26E-001"].schedule_id]
    assert sim.link.uplink_rejected == 0  # the sim reads only validly signed uplink frames
    assert gateway.status()["airframes"][0]["signing"]["unsigned"] == 0


@pytest.mark.anyio
async def test_a_lost_answer_is_sent_again_until_it_is_answered() -> None:
    mem = MemorySink("mem")
    gateway = Gateway(gateway_config(), sinks={"mem": mem})
    sim = SimulatedAirframe(1, fast_profile())
    sim.radio.ignore_first = 2
    await fly(gateway, sim, lambda: gateway.fleet.hops.status()[0]["state"] == "accepted")
    assert gateway.fleet.hops.status()[0]["sends"] == 3
    assert len(sim.radio.schedules) == 3
    assert len(set(sim.radio.schedules)) == 1  # the same schedule, re-sent


@pytest.mark.anyio
async def test_a_plan_the_airframe_cannot_fly_is_refused_and_not_sent_again() -> None:
    mem = MemorySink("mem")
    # 0.3 µs beats the jammer and suits the AD9361, but the simulated radio needs 0.5 µs.
    gateway = Gateway(gateway_config({**PLAN, "dwell_us": 0.3}), sinks={"mem": mem})
    sim = SimulatedAirframe(1, fast_profile())
    await fly(gateway, sim, lambda: gateway.fleet.hops.status()[0]["state"] == "refused")
    (upload,) = gateway.fleet.hops.status()
    assert (upload["last_result"], upload["sends"], upload["active_schedule_id"]) == (
        "unsupported_dwell",
        1,
        "00000000",
    )
    assert sim.radio.active is None
    assert not hop_events(mem)
    answers = gateway.instruments.hop_schedule_answers
    assert answers.labels("F26E-001", "unsupported_dwell").value == 1


@pytest.mark.anyio
async def test_an_airframe_that_reports_another_schedule_gets_the_plan_again() -> None:
    mem = MemorySink("mem")
    gateway = Gateway(gateway_config(), sinks={"mem": mem})
    sim = SimulatedAirframe(1, fast_profile())
    sid = schedule_id(HopPlanConfig.model_validate(PLAN))
    other = hop_schedule_message(HopPlanConfig.model_validate({**PLAN, "dwell_us": 15}), 1, 77)

    def rebooted_with_its_old_plan() -> bool:
        if gateway.fleet.hops.status()[0]["state"] == "accepted" and len(sim.radio.schedules) == 1:
            sim.radio.active = other  # the radio came back on the plan it had stored
        # Done once the gateway has the airframe's answer to the re-send too: the radio may
        # take the schedule a moment before its ACK reaches the gateway (a loaded machine).
        return (
            len(sim.radio.schedules) >= 2
            and sim.radio.active_id == sid
            and gateway.fleet.hops.status()[0]["state"] == "accepted"
        )

    await fly(gateway, sim, rebooted_with_its_old_plan)
    assert sim.radio.schedules[:2] == [sid, sid]
    assert gateway.fleet.hops.status()[0]["state"] == "accepted"


def test_the_radio_answers_each_kind_of_plan() -> None:
    radio = SimRadio(1)
    mine = apm.MAVLink(None, srcSystem=255, srcComponent=191)
    good = HopPlanConfig.model_validate(PLAN)

    def answered(msg: FischerHopSchedule) -> int:
        (back,) = apm.MAVLink(None).parse_buffer(msg.pack(mine))  # as it arrives
        ack = radio.answer(back, 1_763_800_000.0)
        assert ack is not None
        assert (ack.target_system, ack.target_component) == (255, 191)
        return int(ack.result)

    assert answered(hop_schedule_message(good, 1, 5)) == HOP_RESULT_ACCEPTED
    short = hop_schedule_message(good, 1, 6)
    short.dwell = 100
    assert answered(short) == HOP_RESULT_UNSUPPORTED_DWELL
    assert radio.active_id == 5  # a refused plan leaves the old one active
    assert radio.answer(hop_schedule_message(good, 2, 7), 0.0) is None  # another airframe's


@pytest.mark.anyio
async def test_a_flood_of_hop_events_is_counted_but_published_at_a_capped_rate() -> None:
    mem = MemorySink("mem")
    gateway = Gateway(gateway_config(None), sinks={"mem": mem})
    session = gateway.fleet.sessions["F26E-001"]
    now_us = int(datetime.now(UTC).timestamp() * 1e6)
    published: list[HopEvent] = []
    gateway.fleet.hops._publish = lambda e: published.append(e) or True  # type: ignore[assignment,func-returns-value]
    for n in range(5000):
        msg = FischerHopEvent(now_us + n, 2_405_000_000, 9, n + 1, 0, n % 2, -60, 127)
        session.dispatch("l", "FISCHER_HOP_EVENT", msg)
    bad = FischerHopEvent(now_us, 10, 9, 1, 0, 0, -60, 127)  # 10 Hz: no AD9361 channel
    session.dispatch("fleet", "FISCHER_HOP_EVENT", bad)
    inst = gateway.instruments
    counted = sum(inst.hop_events.labels("F26E-001", r).value for r in ("scheduled", "jammed"))
    assert counted == 5000
    assert inst.hops.labels("F26E-001").value == 5000
    assert len(published) <= 2 * (PUBLISH_BURST + 1)  # per reason, in the test's short time
    assert inst.hop_events_dropped.labels("F26E-001").value == 5000 - len(published)
    assert inst.link_rejected.labels("fleet", "malformed").value == 1
    assert published[0].rssi_dbm == -60.0
    assert published[0].interference_dbm is None


NODE = """\
airframes:
  - id: F26E-001
    sysid: 1
    links: [{uri: 'udp://127.0.0.1:14550', security: unsecured}]
    hop_plan:
      frequencies_mhz: FREQS
      bandwidth_mhz: BW
      dwell_us: DWELL
"""


def config_issues(freqs: str = "[2405, 2430]", bw: str = "10", dwell: str = "12") -> list[str]:
    text = NODE.replace("FREQS", freqs).replace("BW", bw).replace("DWELL", dwell)
    try:
        load_config_text(text, "node.yaml")
    except ConfigError as exc:
        return [str(issue) for issue in exc.issues]
    return []


def test_a_flyable_plan_that_beats_the_jammer_loads() -> None:
    assert config_issues() == []
    plan = HopPlanConfig.model_validate(PLAN)
    assert plan.jammer_reaction_us == 20.0  # the default jammer
    assert plan.plan().beats_reactive_jammer(plan.jammer_reaction_s)


@pytest.mark.parametrize(
    ("freqs", "bw", "dwell", "expected"),
    [
        (
            "[2405, 2430]",
            "10",
            "20",
            "node.yaml:8 airframes[0].hop_plan.dwell_us: a dwell of 20 µs does not beat a "
            "reactive jammer reacting in 20 µs (jammer_reaction_us): the dwell must be shorter",
        ),
        ("[2405, 6001]", "10", "12", "node.yaml:6 airframes[0].hop_plan.frequencies_mhz[1]:"),
        ("[2405, 65]", "10", "12", "node.yaml:6 airframes[0].hop_plan.frequencies_mhz[1]:"),
        ("[2405, 2430]", "57", "12", "node.yaml:7 airframes[0].hop_plan.bandwidth_mhz:"),
        ("[2405, 2430]", "0.0000001", "12", "node.yaml:7 airframes[0].hop_plan.bandwidth_mhz:"),
        (
            "[100, 200, 300, 400, 500, 600, 700, 800, 900]",
            "10",
            "12",
            "node.yaml:6 airframes[0].hop_plan.frequencies_mhz:",
        ),
        ("[]", "10", "12", "node.yaml:6 airframes[0].hop_plan.frequencies_mhz:"),
    ],
)
def test_a_plan_the_radio_cannot_fly_is_a_config_error_naming_key_and_line(
    freqs: str, bw: str, dwell: str, expected: str
) -> None:
    (issue,) = config_issues(freqs, bw, dwell)
    assert issue.startswith(expected)


def test_the_plan_is_checked_again_right_before_upload() -> None:
    """A plan that no longer beats the jammer (a changed jammer figure) is never sent."""
    gateway = Gateway(gateway_config(), sinks={"mem": MemorySink("mem")})
    upload = gateway.fleet.hops.uploads["F26E-001"]
    upload.config = upload.config.model_copy(update={"jammer_reaction_us": 10.0})
    assert gateway.fleet.hops._checked_frame(upload) is None
    assert upload.state == "invalid"


u8 = st.integers(0, 255)
u32 = st.integers(0, 2**32 - 1)
u64 = st.integers(0, 2**64 - 1)
i8 = st.integers(-128, 127)


@pytest.mark.anyio
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    event=st.tuples(u64, u64, u32, u32, u8, u8, i8, i8),
    ack=st.tuples(u32, u32, u8, u8, u8),
    noise=st.binary(max_size=64),
)
async def test_any_hop_frame_becomes_an_event_or_a_count_never_an_error(
    event: tuple[int, ...], ack: tuple[int, ...], noise: bytes
) -> None:
    """Hop events and answers with any values, and bytes around them, from the airframe."""
    gateway = Gateway(gateway_config(), sinks={"mem": MemorySink("mem")})
    published: list[HopEvent] = []
    gateway.fleet.hops._publish = lambda e: published.append(e) or True  # type: ignore[assignment,func-returns-value]
    airframe = apm.MAVLink(None, srcSystem=1, srcComponent=1)
    link = next(iter(gateway.fleet.links.values())).label
    for frame in (
        FischerHopEvent(*event).pack(airframe),
        FischerHopScheduleAck(*ack).pack(airframe),
        noise,
        noise + FischerHopEvent(*event).pack(airframe),
    ):
        gateway.fleet.ingest.on_data(link, ("127.0.0.1", 5), frame)
    inst = gateway.instruments
    assert inst.link_ignored.labels(link, "handler_error").value == 0
    counted = sum(inst.hop_events.labels("F26E-001", r).value for r in HOP_REASONS)
    rejected = inst.link_rejected.labels(link, "malformed").value
    assert len(published) <= counted
    assert counted + rejected >= 1  # the first event frame was counted or refused
    assert gateway.fleet.hops.status()[0]["state"] in STATES


@pytest.mark.anyio
async def test_an_answer_nobody_asked_for_is_not_taken() -> None:
    gateway = Gateway(gateway_config(), sinks={"mem": MemorySink("mem")})
    session = gateway.fleet.sessions["F26E-001"]
    sid = gateway.fleet.hops.uploads["F26E-001"].schedule_id
    session.dispatch("l", "FISCHER_HOP_SCHEDULE_ACK", FischerHopScheduleAck(sid, sid, 255, 191, 0))
    (upload,) = gateway.fleet.hops.status()
    assert (upload["state"], upload["last_result"], upload["active_schedule_id"]) == (
        "waiting_link",
        None,
        None,
    )


@pytest.mark.anyio
async def test_an_airframe_back_after_losing_every_link_gets_the_plan_again() -> None:
    """It may have rebooted without the plan; without one it reports no hops to say so."""
    config = gateway_config()
    airframe = config.airframes[0].model_copy(update={"link_timeout_s": 0.5})
    gateway = Gateway(
        config.model_copy(update={"airframes": (airframe,)}), sinks={"mem": MemorySink("mem")}
    )
    upload = gateway.fleet.hops.uploads["F26E-001"]
    before, after = SimulatedAirframe(1, fast_profile()), SimulatedAirframe(1, fast_profile())
    with anyio.fail_after(20):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            port = next(iter(gateway.fleet.links.values())).local_port  # type: ignore[attr-defined]
            async with anyio.create_task_group() as first:
                first.start_soon(lambda: before.run_udp("127.0.0.1", port))
                await eventually(lambda: upload.state == "accepted")
                first.cancel_scope.cancel()
            await eventually(lambda: upload.link_lost)
            tg.start_soon(lambda: after.run_udp("127.0.0.1", port))
            await eventually(lambda: after.radio.active_id == upload.schedule_id)
            await eventually(lambda: upload.state == "accepted")
            gateway.shutdown()
            await gateway.stopped.wait()
            tg.cancel_scope.cancel()
    assert before.radio.schedules == after.radio.schedules == [upload.schedule_id]
    assert upload.sends == 2


def test_the_console_line_of_a_hop() -> None:
    (hop,) = sample_events(frozenset({EventKind.HOP}))
    assert describe(hop) == (
        "12:00:00.000Z hop        F26E-001 jammed to slot 2 2435.000 MHz schedule 1234abcd"
        " hops 41000 rssi -62 dBm interference -31 dBm"
    )


def test_a_signed_link_cannot_take_hop_answers_or_reports_unsigned() -> None:
    """Listing them in accept_unsigned_msgids would let anyone forge an acceptance."""
    text = """\
airframes:
  - id: F26E-001
    sysid: 1
    signing: {key_file: /etc/fischer/F26E-001.key, accept_unsigned_msgids: [109, 61004]}
    links: [{uri: 'udp://127.0.0.1:14550', security: signed}]
"""
    with pytest.raises(ConfigError) as raised:
        load_config_text(text, "node.yaml")
    (issue,) = (str(issue) for issue in raised.value.issues)
    assert issue.startswith(
        "node.yaml:4 airframes[0].signing.accept_unsigned_msgids: 61004 (FISCHER_HOP_EVENT) "
        "cannot be accepted unsigned"
    )
    assert SIGNED_ONLY_MSGIDS == {
        MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE_ACK: "FISCHER_HOP_SCHEDULE_ACK",
        MAVLINK_MSG_ID_FISCHER_HOP_EVENT: "FISCHER_HOP_EVENT",
    }


@settings(max_examples=100, deadline=None)
@given(
    schedule=st.tuples(
        u64,
        st.lists(u64, min_size=8, max_size=8),
        st.integers(1, 2**32 - 1),
        u32,
        u32,
        u32,
        u8,
        u8,
        u8,
    ),
    at=st.floats(0, 4e9),
)
def test_a_radio_forced_to_accept_reports_hops_on_any_schedule(
    schedule: tuple[Any, ...], at: float
) -> None:
    """``simulate --hop-result accepted`` takes whatever arrives (0 ns dwell, 0 slots ...)."""
    radio = SimRadio(1, result=HOP_RESULT_ACCEPTED)
    msg = FischerHopSchedule(*schedule)
    msg.target_system, msg.target_component = 1, 0
    (back,) = apm.MAVLink(None).parse_buffer(msg.pack(apm.MAVLink(None, 255, 191)))
    assert radio.answer(back, at) is not None
    (event,) = radio.events_at(at + 1.0)
    assert 0 <= event.slot < 8
