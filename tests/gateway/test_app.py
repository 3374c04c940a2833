"""The whole gateway on loopback: simulator → UDP → ingest → bus → sinks, health, shutdown."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import anyio
import pytest

from gateway.app import Gateway
from gateway.config import Config
from gateway.events import Telemetry, event_adapter
from gateway.fleet.tlog import replay_udp
from gateway.sim.airframe import SimulatedAirframe
from gateway.testing import MemorySink, eventually

CORPUS = Path(__file__).resolve().parents[2].parent / "shared" / "corpus"
SMALL_TLOG = CORPUS / "mavlink" / "arducopter_hw_ground_small.tlog"


def config(tmp_path: Path, *sinks: str, udp_port: int = 0) -> Config:
    extra = [{"name": name, "type": "memory"} for name in sinks]
    return Config.model_validate(
        {
            "gateway": {"shutdown_deadline_s": 2},
            "health": {"port": 0},
            "airframes": [
                {
                    "id": "F26E-001",
                    "sysid": 1,
                    "links": [{"uri": f"udp://127.0.0.1:{udp_port}", "security": "unsecured"}],
                },
                {
                    "id": "F26E-002",
                    "sysid": 2,
                    "links": [{"uri": f"udp://127.0.0.1:{udp_port}", "security": "unsecured"}],
                },
            ],
            "sinks": [
                {
                    "name": "archive",
                    "type": "jsonl",
                    "options": {"path": str(tmp_path / "a.jsonl")},
                },
                {"name": "mem", "type": "memory"},
                *extra,
            ],
            "routes": [{"sinks": ["archive", "mem", *sinks]}],
        }
    )


def udp_port(gateway: Gateway) -> int:
    link = next(iter(gateway.fleet.links.values()))
    return int(link.local_port)  # type: ignore[attr-defined]


async def http_get(port: int, path: str) -> tuple[int, bytes]:
    async with await anyio.connect_tcp("127.0.0.1", port) as stream:
        await stream.send(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        data = b""
        while True:
            try:
                data += await stream.receive()
            except anyio.EndOfStream:
                break
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


@pytest.mark.anyio
async def test_simulated_positions_arrive_unchanged_in_jsonl_and_memory(tmp_path: Path) -> None:
    mem = MemorySink("mem")
    gateway = Gateway(config(tmp_path), sinks={"mem": mem})
    sims = [SimulatedAirframe(1), SimulatedAirframe(2, phase_rad=1.0)]
    with anyio.fail_after(20):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            port = udp_port(gateway)
            async with anyio.create_task_group() as fleet:
                for sim in sims:
                    fleet.start_soon(
                        lambda s=sim: s.run_udp("127.0.0.1", port, duration_s=2.0, speed=4.0)
                    )
            # The last position sent by each airframe must be the last one each sink has.
            while True:
                last = {
                    e.airframe: e.position
                    for e in mem.events
                    if isinstance(e, Telemetry) and e.position is not None
                }
                if len(last) == 2:
                    break
                await anyio.sleep(0.01)
            gateway.shutdown()
    sent = {
        f"F26E-00{sim_index + 1}": {
            (p.lat_e7 / 1e7, p.lon_e7 / 1e7, p.alt_mm / 1000.0) for p in sim.sent_positions
        }
        for sim_index, sim in enumerate(sims)
    }
    archived = [
        event_adapter.validate_json(line)
        for line in (tmp_path / "a.jsonl").read_text().splitlines()
    ]
    for received in (mem.events, archived):
        positions = [
            (e.airframe, e.position)
            for e in received
            if isinstance(e, Telemetry) and e.position is not None
        ]
        assert len(positions) > 20
        for airframe, pos in positions:
            assert pos is not None
            assert (pos.lat_deg, pos.lon_deg, pos.alt_msl_m) in sent[airframe]
        for index, sim in enumerate(sims):
            final = sim.sent_positions[-1]
            mine = [p for a, p in positions if a == f"F26E-00{index + 1}"]
            assert mine[-1] is not None
            assert (mine[-1].lat_deg, mine[-1].lon_deg) == (final.lat_e7 / 1e7, final.lon_e7 / 1e7)


def last_lat(sink: MemorySink) -> float | None:
    for event in reversed(sink.events):
        if isinstance(event, Telemetry) and event.position is not None:
            return event.position.lat_deg
    return None


@pytest.mark.anyio
async def test_failing_and_hung_sinks_leave_ingest_and_others_unchanged(tmp_path: Path) -> None:
    async def run(extra: dict[str, MemorySink]) -> tuple[float, int]:
        mem = MemorySink("mem")
        gateway = Gateway(config(tmp_path, *extra), sinks={"mem": mem, **extra})
        sim = SimulatedAirframe(1)
        with anyio.fail_after(20):
            async with anyio.create_task_group() as tg:
                await tg.start(gateway.run)
                await sim.run_udp("127.0.0.1", udp_port(gateway), duration_s=3.0, speed=10.0)
                final = sim.sent_positions[-1]
                await eventually(lambda: last_lat(mem) == final.lat_e7 / 1e7)
                label = next(iter(gateway.fleet.links.values())).label
                frames = gateway.instruments.link_frames.labels(label).value
                gateway.shutdown()
        return last_lat(mem), int(frames)

    failing, hung = MemorySink("failing"), MemorySink("hung")
    failing.fail_transient = True
    hung.hang = True
    baseline = await run({})
    with_bad = await run({"failing": failing, "hung": hung})
    assert with_bad == baseline
    assert not hung.events
    assert not failing.events


@pytest.mark.anyio
async def test_health_endpoints_report_links_sinks_and_metrics(tmp_path: Path) -> None:
    gateway = Gateway(config(tmp_path))
    with anyio.fail_after(20):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            assert gateway.health_port
            sim = SimulatedAirframe(1)
            await sim.run_udp("127.0.0.1", udp_port(gateway), duration_s=1.0, speed=10.0)
            await eventually(gateway.is_ready)
            code, _ = await http_get(gateway.health_port, "/readyz")
            assert code == 200
            code, body = await http_get(gateway.health_port, "/status")
            status = json.loads(body)
            assert status["airframes"][0]["links"][0]["up"] is True
            assert {s["sink"] for s in status["sinks"]} == {"archive", "mem"}
            code, body = await http_get(gateway.health_port, "/metrics")
            text = body.decode()
            assert 'fg_link_frames_total{link="udp://127.0.0.1:' in text
            assert 'fg_events_total{kind="telemetry"}' in text
            assert 'fg_sink_delivery_latency_seconds_bucket{sink="mem"' in text
            assert 'fg_sink_queue_depth{sink="mem",class="durable"} 0' in text
            gateway.shutdown()


@pytest.mark.corpus
@pytest.mark.anyio
async def test_replayed_corpus_tlog_reaches_sinks_with_pymavlink_positions(tmp_path: Path) -> None:
    if not SMALL_TLOG.exists():
        pytest.skip("shared corpus absent")
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(SMALL_TLOG), robust_parsing=True)
    expected = set()
    while (msg := conn.recv_match(type="GLOBAL_POSITION_INT")) is not None:
        expected.add((msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0))
    conn.close()
    mem = MemorySink("mem")
    gateway = Gateway(config(tmp_path), sinks={"mem": mem})
    with anyio.fail_after(30):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            sent = await replay_udp(SMALL_TLOG, "127.0.0.1", udp_port(gateway), speed=50.0)
            assert sent > 4000
            await anyio.sleep(0.2)
            gateway.shutdown()
    got = [
        (e.position.lat_deg, e.position.lon_deg, e.position.alt_msl_m)
        for e in mem.events
        if isinstance(e, Telemetry) and e.position is not None
    ]
    assert got
    assert set(got) <= expected


def test_sigterm_stops_the_daemon_within_the_deadline(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(
        "gateway: {shutdown_deadline_s: 2}\nhealth: {port: 0}\n"
        "airframes:\n  - {id: A, sysid: 1, links: "
        "[{uri: 'udp://127.0.0.1:0', security: unsecured}]}\n"
        f"sinks:\n  - {{name: j, type: jsonl, options: {{path: '{tmp_path / 'a.jsonl'}'}}}}\n"
        "routes:\n  - {sinks: [j]}\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway", "run", "--config", str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert proc.stdout is not None
    lines = []
    for raw in proc.stdout:
        lines.append(json.loads(raw))
        if lines[-1]["event"] == "gateway_started":
            break
    started = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=10)
    elapsed = time.monotonic() - started
    assert proc.returncode == 0
    assert elapsed < 2.0 + 1.0  # the deadline, plus interpreter exit
    events = [json.loads(line)["event"] for line in rest.splitlines()]
    assert events[-1] == "gateway_stopped"
    assert "signal_received" in events


def test_demo_runs_for_its_duration_and_archives_events(tmp_path: Path) -> None:
    archive = tmp_path / "demo.jsonl"
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "demo", "--duration", "2", "--udp-port", "0",
         "--health-port", "0", "--archive", str(archive)],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "[2/10] GUTE II battery registered: GUTE-1" in result.stdout
    assert "stopped before the operation ended; not reached: [" in result.stdout
    kinds = {json.loads(line)["kind"] for line in archive.read_text().splitlines()}
    assert {"telemetry", "link_state"} <= kinds


def test_port_in_use_is_a_clear_error_and_exit_1(tmp_path: Path) -> None:
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        path = tmp_path / "c.yaml"
        path.write_text(
            f"health: {{port: {port}}}\n"
            "airframes:\n  - {id: A, sysid: 1, links: "
            "[{uri: 'udp://127.0.0.1:0', security: unsecured}]}\n"
        )
        result = subprocess.run(
            [sys.executable, "-m", "gateway", "run", "--config", str(path)],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
    assert result.returncode == 1
    assert f"health endpoint 127.0.0.1:{port}: cannot listen" in result.stderr  # logs: stderr
