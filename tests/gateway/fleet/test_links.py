"""Transports on real sockets and a real pseudo-terminal: serial, TCP client and server."""

from __future__ import annotations

import os
import tty

import anyio
import anyio.abc
import pytest

from gateway.app import Gateway
from gateway.config import Config
from gateway.events import Telemetry
from gateway.sim.airframe import SimulatedAirframe
from gateway.testing import MemorySink, eventually


def gateway_with(uri: str) -> tuple[Gateway, MemorySink]:
    config = Config.model_validate(
        {
            "gateway": {"shutdown_deadline_s": 1},
            "health": {"enabled": False},
            "airframes": [
                {
                    "id": "F26E-001",
                    "sysid": 1,
                    "links": [
                        {
                            "uri": uri,
                            "security": "unsecured",
                            "reconnect_initial_s": 0.05,
                            "reconnect_max_s": 0.2,
                        }
                    ],
                }
            ],
            "sinks": [{"name": "mem", "type": "memory"}],
            "routes": [{"sinks": ["mem"]}],
        }
    )
    mem = MemorySink("mem")
    return Gateway(config, sinks={"mem": mem}), mem


def latest_lat(mem: MemorySink) -> float | None:
    for event in reversed(mem.events):
        if isinstance(event, Telemetry) and event.position is not None:
            return event.position.lat_deg
    return None


@pytest.mark.anyio
async def test_serial_link_reads_a_pseudo_terminal() -> None:
    master, slave = os.openpty()
    tty.setraw(master)
    device = os.ttyname(slave)
    gateway, mem = gateway_with(f"serial://{device}?baud=57600")
    sim = SimulatedAirframe(1)
    try:
        with anyio.fail_after(10):
            async with anyio.create_task_group() as tg:
                await tg.start(gateway.run)
                stream = b"".join(sim.frames_at(0.0) + sim.frames_at(1.0))
                # A radio modem delivers bytes, not frames: write in odd-sized pieces.
                for start in range(0, len(stream), 7):
                    os.write(master, stream[start : start + 7])
                final = sim.sent_positions[-1]
                await eventually(lambda: latest_lat(mem) == final.lat_e7 / 1e7)
                gateway.shutdown()
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.anyio
async def test_tcp_client_reconnects_after_the_peer_hangs_up() -> None:
    sim = SimulatedAirframe(1)
    connections = 0

    async def serve(stream: anyio.abc.SocketStream) -> None:
        nonlocal connections
        connections += 1
        async with stream:
            await stream.send(b"".join(sim.frames_at(float(connections))))
        # Closing the stream is the peer hanging up: the gateway must reconnect.

    listener = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=0)
    port = listener.extra(anyio.abc.SocketAttribute.local_port)
    gateway, mem = gateway_with(f"tcp://127.0.0.1:{port}")
    with anyio.fail_after(15):
        async with listener, anyio.create_task_group() as tg:
            tg.start_soon(listener.serve, serve)
            await tg.start(gateway.run)
            await eventually(lambda: connections >= 3)
            final = sim.sent_positions[-1]
            await eventually(lambda: latest_lat(mem) == final.lat_e7 / 1e7)
            link = next(iter(gateway.fleet.links.values()))
            assert link.connects >= 3
            gateway.shutdown()
            await gateway.stopped.wait()
            tg.cancel_scope.cancel()


@pytest.mark.anyio
async def test_tcp_server_link_takes_several_peers() -> None:
    gateway, mem = gateway_with("tcp://127.0.0.1:0?mode=listen")
    one, two = SimulatedAirframe(1), SimulatedAirframe(1, phase_rad=2.0)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            port = next(iter(gateway.fleet.links.values())).local_port  # type: ignore[attr-defined]
            async with await anyio.connect_tcp("127.0.0.1", port) as a:
                await a.send(b"".join(one.frames_at(0.0)))
                await eventually(lambda: latest_lat(mem) == one.sent_positions[-1].lat_e7 / 1e7)
            async with await anyio.connect_tcp("127.0.0.1", port) as b:
                await b.send(b"".join(two.frames_at(0.0)))
                await eventually(lambda: latest_lat(mem) == two.sent_positions[-1].lat_e7 / 1e7)
            gateway.shutdown()


@pytest.mark.anyio
async def test_missing_serial_device_is_named_and_retried_not_fatal() -> None:
    gateway, _ = gateway_with("serial:///dev/does-not-exist?baud=57600")
    with anyio.fail_after(5):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            link = next(iter(gateway.fleet.links.values()))
            await eventually(lambda: link.connects == 0 and link.state == "waiting for device")
            assert "/dev/does-not-exist" in link.reason
            assert gateway.is_ready()
            gateway.shutdown()
