"""The CoT sink's ``send_now``: UDP datagrams in the delivery pass, ``send`` for the rest.

Real sockets on loopback. A socket whose buffer is full (``BlockingIOError``) stops the pass
at that event; the runner's task sends it and the rest, so each receiver gets every event once
and in order.
"""

from __future__ import annotations

import re
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from typing import Any

import anyio
import anyio.lowlevel
import pytest

from gateway.c2.sinkrunner import SinkRunner
from gateway.config import SinkEntry
from gateway.events import Detection, Position, Sensor
from gateway.ops.instruments import Instruments
from gateway.testing import eventually
from sinks.cot.sink import CotSink, CotSinkConfig
from sinks.cot.udp import UdpSender

T0 = datetime(2026, 11, 27, 12, 0, tzinfo=UTC)
UID = re.compile(rb'uid="fischer-det-(det-\d+)"')


def detection(n: int) -> Detection:
    return Detection(
        event_id=f"det-{n}",
        airframe="F26E-001",
        time=T0,
        sensor=Sensor.EO,
        object_class="tank",
        confidence=0.9,
        position=Position(lat_deg=65.1, lon_deg=21.1),
        sigma_h_m=5.0,
    )


class FullOnce:
    """A connected UDP socket whose buffer is full for the ``full_at``-th datagram, once."""

    def __init__(self, sock: socket.socket, full_at: int) -> None:
        self.sock = sock
        self.full_at = full_at
        self.sends = 0

    def send(self, data: bytes) -> int:
        self.sends += 1
        if self.sends == self.full_at:
            raise BlockingIOError(11, "Resource temporarily unavailable")
        return self.sock.send(data)

    def fileno(self) -> int:
        return self.sock.fileno()

    def close(self) -> None:
        self.sock.close()


@contextmanager
def receivers(count: int) -> Iterator[list[socket.socket]]:
    socks = []
    try:
        for _ in range(count):
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
            sock.setblocking(False)
            socks.append(sock)
        yield socks
    finally:
        for sock in socks:
            sock.close()


def received(sock: socket.socket, into: list[str]) -> None:
    while True:
        try:
            data = sock.recv(65_535)
        except BlockingIOError:
            return
        into.extend(m.decode() for m in UID.findall(data))


def cot_sink(*ports: int, **extra: Any) -> CotSink:
    destinations = [f"udp://127.0.0.1:{port}" for port in ports]
    return CotSink("cot", CotSinkConfig.model_validate({"destinations": destinations, **extra}))


def test_only_a_sink_with_udp_destinations_only_sends_now() -> None:
    assert callable(cot_sink(9).send_now)
    mixed = CotSink(
        "cot",
        CotSinkConfig.model_validate({"destinations": ["udp://127.0.0.1:9", "tcp://127.0.0.1:9"]}),
    )
    assert mixed.send_now is None  # a TAK server stream may block: the task sends


@pytest.mark.anyio
async def test_a_full_socket_buffer_hands_the_rest_to_the_runner_in_order() -> None:
    inst = Instruments()
    with receivers(2) as socks, anyio.fail_after(10):
        cot = cot_sink(*(s.getsockname()[1] for s in socks))
        runner = SinkRunner(SinkEntry(name="cot", type="cot"), cot, inst)
        got: list[list[str]] = [[], []]
        async with anyio.create_task_group() as tg:
            await tg.start(runner.run)
            await eventually(lambda: runner.state == "open")
            await anyio.lowlevel.checkpoint()
            for n in range(3):
                runner.offer(detection(n), 0.0)
                await anyio.lowlevel.checkpoint()
            assert runner.sent_in_pass == 3
            transports = [t for t in cot._transports if isinstance(t, UdpSender)]
            second = transports[1]._datagrams
            real = second._sock
            assert real is not None
            second._sock = FullOnce(real, full_at=3)  # type: ignore[assignment]
            for n in range(3, 9):
                runner.offer(detection(n), 0.0)  # one pass: one batch of six
            await anyio.lowlevel.checkpoint()

            def arrived() -> bool:
                for sock, ids in zip(socks, got, strict=True):
                    received(sock, ids)
                return all(len(ids) >= 9 for ids in got) or any(len(ids) > 9 for ids in got)

            await eventually(arrived)
            tg.cancel_scope.cancel()
    expected = [f"det-{n}" for n in range(9)]
    # The second receiver's buffer was full for det-5: the pass stopped there and the task
    # sent det-5 on, to both (the first had it already: a CoT receiver replaces by uid).
    assert got[1] == expected
    assert got[0] == [*expected[:6], "det-5", *expected[6:]]
    assert runner.sent_in_pass == 5
    assert inst.sink_sent.labels("cot").value == 9
    assert inst.sink_latency.labels("cot").count == 9
