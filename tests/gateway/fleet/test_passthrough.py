"""The passthrough: MAVSDK, a real MAVLink implementation, works through the gateway."""

from __future__ import annotations

import math
from contextlib import aclosing

import anyio
import pytest
from daemon_support import free_udp_port
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.app import Gateway
from gateway.config import Config
from gateway.sim.airframe import SimulatedAirframe
from gateway.testing import eventually

mavsdk = pytest.importorskip("mavsdk.asyncio")
telemetry_plugin = pytest.importorskip("mavsdk.asyncio.plugins.telemetry")


@pytest.mark.parametrize("anyio_backend", [("asyncio", {})], ids=["asyncio"])
@pytest.mark.anyio
async def test_mavsdk_gets_position_and_battery_through_the_passthrough() -> None:
    gcs_port = free_udp_port()
    config = Config.model_validate(
        {
            "health": {"enabled": False},
            "airframes": [
                {
                    "id": "F26E-001",
                    "sysid": 1,
                    "links": [{"uri": "udp://127.0.0.1:0", "security": "unsecured"}],
                    "passthrough": {
                        "uri": f"udp://127.0.0.1:{gcs_port}?mode=connect",
                        "uplink": "open",
                    },
                }
            ],
        }
    )
    gateway = Gateway(config)
    sim = SimulatedAirframe(1)
    uplinked: list[str] = []
    settings = mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
    with anyio.fail_after(30):
        async with mavsdk.Mavsdk(settings) as gcs, anyio.create_task_group() as tg:
            await gcs.add_any_connection(f"udpin://127.0.0.1:{gcs_port}")
            await tg.start(gateway.run)
            port = int(next(iter(gateway.fleet.links.values())).local_port)  # type: ignore[attr-defined]
            sock = await anyio.create_connected_udp_socket(
                remote_host="127.0.0.1", remote_port=port
            )

            async def fly() -> None:
                t = 0.0
                while True:
                    for frame in sim.frames_at(t):
                        await sock.send(frame)
                    t += 0.05
                    await anyio.sleep(0.05)

            async def listen() -> None:
                parser = mav.MAVLink(None)
                async for data in sock:
                    for msg in parser.parse_buffer(data) or ():
                        uplinked.append(msg.get_type())

            tg.start_soon(fly)
            tg.start_soon(listen)
            system = await gcs.first_autopilot(timeout_s=20.0)
            assert system is not None
            telemetry = telemetry_plugin.TelemetryAsync(system)
            async with aclosing(telemetry.subscribe_position()) as updates:
                position = await anext(updates)
            async with aclosing(telemetry.subscribe_battery()) as updates:
                battery = await anext(updates)
            await eventually(lambda: "HEARTBEAT" in uplinked)
            tg.cancel_scope.cancel()
        await sock.aclose()
    sent = {(p.lat_e7 / 1e7, p.lon_e7 / 1e7) for p in sim.sent_positions}
    assert any(
        math.isclose(position.latitude_deg, lat, abs_tol=1e-7)
        and math.isclose(position.longitude_deg, lon, abs_tol=1e-7)
        for lat, lon in sent
    )
    assert 0 < battery.remaining_percent <= 100
    assert 18.0 < battery.voltage_v < 26.0  # the simulated 6S pack
    assert gateway.fleet.passthroughs["F26E-001"].downlink_frames > 0
