"""The daemon as operators see it: systemd STATUS=, process and readiness metrics, DEM state."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import anyio
import pytest
from prometheus_client import ProcessCollector
from prometheus_client.parser import text_string_to_metric_families

from gateway.app import Gateway
from gateway.config import Config
from gateway.ops.sdnotify import SystemdNotifier
from gateway.ops.version import package_version
from gateway.sim.airframe import SimulatedAirframe
from gateway.testing import MemorySink


def config(tmp_path: Path, **extra: Any) -> Config:
    link = {"uri": "udp://127.0.0.1:0", "security": "unsecured"}
    return Config.model_validate(
        {
            "gateway": {"shutdown_deadline_s": 1},
            "health": {"port": 0},
            "airframes": [
                {"id": "F26E-001", "sysid": 1, "links": [link]},
                {"id": "F26E-002", "sysid": 2, "links": [link]},
            ],
            "sinks": [{"name": "mem", "type": "memory"}],
            "routes": [{"sinks": ["mem"]}],
            **extra,
        }
    )


def udp_port(gateway: Gateway) -> int:
    link = next(iter(gateway.fleet.links.values()))
    return int(link.local_port)  # type: ignore[attr-defined]


def samples(gateway: Gateway) -> dict[str, float]:
    """Every unlabelled-or-labelled sample of /metrics' text, by its full series name."""
    out = {}
    for family in text_string_to_metric_families(gateway.instruments.registry.render()):
        for sample in family.samples:
            labels = ",".join(f'{k}="{v}"' for k, v in sorted(sample.labels.items()))
            out[f"{sample.name}{{{labels}}}" if labels else sample.name] = sample.value
    return out


@pytest.mark.anyio
async def test_status_is_refreshed_with_airframes_linked_and_sinks_healthy(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    notifier = SystemdNotifier({"NOTIFY_SOCKET": path}, status_interval_s=0.02)
    gateway = Gateway(config(tmp_path), sinks={"mem": MemorySink("mem")}, notifier=notifier)
    async with await anyio.create_unix_datagram_socket(local_path=path) as systemd:
        with anyio.fail_after(10):
            async with anyio.create_task_group() as tg:
                await tg.start(gateway.run)
                ready = (await systemd.receive())[0].decode()
                assert ready.startswith("READY=1\nSTATUS=0/2 airframes linked, 1/1 sinks healthy")
                await SimulatedAirframe(1).run_udp(
                    "127.0.0.1", udp_port(gateway), duration_s=0.5, speed=10.0
                )
                while True:
                    message = (await systemd.receive())[0].decode()
                    if message.startswith("STATUS=1/2 airframes linked"):
                        break
                assert message == "STATUS=1/2 airframes linked, 1/1 sinks healthy"
                gateway.shutdown()


@pytest.mark.anyio
async def test_metrics_carry_process_build_info_and_readiness(tmp_path: Path) -> None:
    gateway = Gateway(config(tmp_path), sinks={"mem": MemorySink("mem")})
    before = samples(gateway)
    assert before["fg_ready"] == 0
    assert before[f'fg_build_info{{version="{package_version()}"}}'] == 1
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            assert samples(gateway)["fg_ready"] == 1
            ours = samples(gateway)
            # prometheus_client's own process collector reads the same process independently.
            theirs = {
                s.name: s.value
                for family in ProcessCollector(pid=lambda: "self", registry=None).collect()
                for s in family.samples
            }
            gateway.shutdown()
    assert ours["process_max_fds"] == theirs["process_max_fds"]
    assert abs(ours["process_open_fds"] - theirs["process_open_fds"]) <= 5
    assert abs(ours["process_start_time_seconds"] - theirs["process_start_time_seconds"]) < 1.5
    assert ours["process_resident_memory_bytes"] == pytest.approx(
        theirs["process_resident_memory_bytes"], rel=0.1
    )
    assert 0 < ours["process_cpu_seconds_total"] <= theirs["process_cpu_seconds_total"] + 0.05
    assert ours["process_open_fds"] == pytest.approx(len(os.listdir("/proc/self/fd")), abs=5)


@pytest.mark.anyio
async def test_a_missing_dem_directory_is_reported_and_the_gateway_runs(tmp_path: Path) -> None:
    """The example config's GeoTIFF directory does not exist on a fresh node."""
    terrain = {
        "sources": [
            {"name": "lm", "kind": "geotiff", "directory": str(tmp_path / "no"), "sigma_m": 0.5}
        ]
    }
    mem = MemorySink("mem")
    gateway = Gateway(config(tmp_path, terrain=terrain), sinks={"mem": mem})
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            await SimulatedAirframe(1).run_udp(
                "127.0.0.1", udp_port(gateway), duration_s=0.5, speed=10.0
            )
            await mem.wait_for(1)
            status = gateway.status()
            line = gateway.status_line()
            gateway.shutdown()
    assert [(t["source"], t["state"]) for t in status["terrain"]] == [("lm", "disabled")]
    assert line.endswith("; DEM disabled: lm")
    metrics = samples(gateway)
    assert metrics['fg_dem_source_up{source="lm"}'] == 0
    assert metrics['fg_dem_errors_total{reason="missing",source="lm"}'] == 1
