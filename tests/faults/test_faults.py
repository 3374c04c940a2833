"""Fault injection, bounded in time: hung sinks, outages, full disks, midnight key rotation."""

from __future__ import annotations

from datetime import UTC, date, datetime, timedelta
from pathlib import Path

import anyio
import pytest

from gateway.app import Gateway
from gateway.config import Config
from gateway.events import Detection, Position, Sensor, Telemetry
from gateway.fleet.security.tunnel import DayKeys, Sealer, derive_day_key
from gateway.sim.airframe import SimulatedAirframe
from gateway.testing import MemorySink, eventually

MASTER = bytes(range(32))


def gateway_config(tmp_path: Path, sinks: list[dict[str, object]], **extra: object) -> Config:
    link = {"uri": "udp://127.0.0.1:0", "security": extra.pop("security", "unsecured")}
    return Config.model_validate(
        {
            "gateway": {"shutdown_deadline_s": 1},
            "health": {"enabled": False},
            "airframes": [{"id": "F26E-001", "sysid": 1, "links": [link]}],
            "sinks": sinks,
            "routes": [{"sinks": [s["name"] for s in sinks]}],
            **extra,
        }
    )


def port(gateway: Gateway) -> int:
    return int(next(iter(gateway.fleet.links.values())).local_port)  # type: ignore[attr-defined]


def detection(n: int) -> Detection:
    return Detection(
        event_id=f"det-{n}",
        airframe="F26E-001",
        time=datetime.now(UTC),
        sensor=Sensor.IR,
        object_class="tank",
        confidence=0.8,
        position=Position(lat_deg=65.9, lon_deg=21.7),
        sigma_h_m=4.0,
    )


@pytest.mark.anyio
async def test_a_hung_sink_holds_up_no_other_sink(tmp_path: Path) -> None:
    """A sink whose send never returns (and whose deadline is an hour) leaves the others
    delivering everything: live telemetry and durable detections. How fast they deliver is
    measured in bench/, not asserted here (a loaded machine would make any bound flaky)."""
    sinks: list[dict[str, object]] = [
        {"name": "good", "type": "memory"},
        {"name": "hung", "type": "memory", "send_timeout_s": 3600},
    ]
    good, hung = MemorySink("good"), MemorySink("hung")
    hung.hang = True
    gateway = Gateway(gateway_config(tmp_path, sinks), sinks={"good": good, "hung": hung})
    sim = SimulatedAirframe(1)
    with anyio.fail_after(60):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            await sim.run_udp("127.0.0.1", port(gateway), duration_s=1.0, speed=4.0)
            for n in range(20):
                gateway.bus.publish(detection(n))
            await eventually(lambda: sum(isinstance(e, Detection) for e in good.events) == 20)
            final = sim.sent_positions[-1]
            await eventually(
                lambda: any(
                    isinstance(e, Telemetry)
                    and e.position is not None
                    and e.position.lat_deg == final.lat_e7 / 1e7
                    for e in good.events
                )
            )
            assert hung.events == []  # still inside its first send
            gateway.shutdown()


@pytest.mark.anyio
async def test_sink_outage_loses_no_durable_event(tmp_path: Path) -> None:
    sink = MemorySink("c2")
    sink.fail_transient = True
    sinks: list[dict[str, object]] = [
        {"name": "c2", "type": "memory", "retry_initial_s": 0.01, "retry_max_s": 0.05}
    ]
    gateway = Gateway(gateway_config(tmp_path, sinks), sinks={"c2": sink})
    with anyio.fail_after(20):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            for n in range(500):
                gateway.bus.publish(detection(n))
            await eventually(lambda: gateway.runners["c2"].failures_in_row >= 3)
            sink.fail_transient = False  # the C2 system is back
            await sink.wait_for(500)
            gateway.shutdown()
    assert [e.event_id for e in sink.events if isinstance(e, Detection)] == [
        f"det-{n}" for n in range(500)
    ]


@pytest.mark.anyio
async def test_full_disk_under_the_archive_is_reported_and_ingest_goes_on(
    tmp_path: Path,
) -> None:
    if not await anyio.Path("/dev/full").exists():
        pytest.skip("/dev/full is not available")
    sinks: list[dict[str, object]] = [
        {"name": "archive", "type": "jsonl", "options": {"path": "/dev/full"}},
        {"name": "live", "type": "memory"},
    ]
    live = MemorySink("live")
    gateway = Gateway(gateway_config(tmp_path, sinks), sinks={"live": live})
    sim = SimulatedAirframe(1)
    with anyio.fail_after(20):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            await sim.run_udp("127.0.0.1", port(gateway), duration_s=1.0, speed=4.0)
            final = sim.sent_positions[-1]
            await eventually(
                lambda: any(
                    isinstance(e, Telemetry)
                    and e.position is not None
                    and e.position.lat_deg == final.lat_e7 / 1e7
                    for e in live.events
                )
            )
            await eventually(lambda: gateway.runners["archive"].state == "retrying")
            reason = gateway.runners["archive"].reason
            gateway.shutdown()
    assert "disk full" in reason
    assert "archive" in reason


class Clock:
    def __init__(self, now: datetime) -> None:
        self.now = now

    def __call__(self) -> datetime:
        return self.now


@pytest.mark.anyio
async def test_clock_jump_across_midnight_rotates_keys_with_grace(tmp_path: Path) -> None:
    key_file = tmp_path / "master.key"
    key_file.write_text(MASTER.hex())
    key_file.chmod(0o600)
    before = datetime(2026, 11, 22, 23, 59, 58, tzinfo=UTC)
    clock = Clock(before)
    mem = MemorySink("mem")
    config = gateway_config(
        tmp_path,
        [{"name": "mem", "type": "memory"}],
        security="tunnel",
        tunnel={"master_key_file": str(key_file), "grace_s": 60, "freshness_s": 3600},
    )
    gateway = Gateway(config, sinks={"mem": mem}, clock=clock)
    days = (date(2026, 11, 22), date(2026, 11, 23))
    airframe_keys = DayKeys(
        keys={("F26E-001", d): derive_day_key(MASTER, "F26E-001", d) for d in days}
    )
    airframe_clock = Clock(before)
    sealer = Sealer("F26E-001", airframe_keys, airframe_clock)
    sim = SimulatedAirframe(1)
    label = next(iter(gateway.fleet.links.values())).label

    sim_time = [0.0]

    async def send(count: int) -> None:
        async with await anyio.create_connected_udp_socket(
            remote_host="127.0.0.1", remote_port=port(gateway)
        ) as sock:
            for _ in range(count):
                # A second of sim time per step: every message group is due each time.
                sim_time[0] += 1.0
                for frame in sim.frames_at(sim_time[0]):
                    await sock.send(sealer.seal(frame))

    def accepted() -> float:
        return gateway.instruments.link_frames.labels(label).value

    with anyio.fail_after(20):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            await send(1)
            await eventually(lambda: accepted() > 0)
            # The gateway's clock jumps past midnight; the airframe's is still on yesterday.
            clock.now = before + timedelta(seconds=5)
            seen = accepted()
            await send(1)
            await eventually(lambda: accepted() > seen)
            # Past the grace window yesterday's key is refused ...
            clock.now = before + timedelta(seconds=120)
            await send(1)
            await eventually(
                lambda: gateway.instruments.link_rejected.labels(label, "auth").value > 0
            )
            # ... and the airframe, once its clock rolls over, is accepted with today's key.
            airframe_clock.now = clock.now
            seen = accepted()
            await send(1)
            await eventually(lambda: accepted() > seen)
            gateway.shutdown()
