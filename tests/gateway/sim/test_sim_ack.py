"""The simulated airframe against a pymavlink ground station: re-sends until acknowledged.

Real UDP sockets on 127.0.0.1. The ground station (``tests/ack_peer.py``) decodes and encodes
with the module mavgen generates from the dialect XML. It cuts the link for a while, answers
some detections first with a decoy the airframe must ignore and acknowledges them only when
they come again, and the airframe must end with every detection delivered, each re-send
identical to the original, and nothing held. Plain, signed and sealed in the tunnel.
"""

from __future__ import annotations

import hashlib
import socket
from datetime import UTC, datetime, timedelta
from functools import partial
from types import ModuleType

import anyio
import anyio.abc
import pytest
from ack_peer import AckPeer, Answer, Arrival, generate_dialect

from gateway.fleet.security.tunnel import DayKeys, Sealer, derive_day_key
from gateway.sim.airframe import SimProfile, SimulatedAirframe
from gateway.sim.resend import ResendPolicy

MASTER = hashlib.sha256(b"detection-ack master").digest()
SIGNING_KEY = hashlib.sha256(b"detection-ack signing").digest()
AIRFRAME = "F26E-007"
SYSID = 7
#: Detections at 20 Hz of sim time and little else, so a short run holds many of them.
PROFILE = SimProfile(detection_hz=20.0, position_hz=5.0, gps_hz=1.0, status_hz=1.0)
#: Fast enough for a test: first re-send after 0.1 s, at most 0.4 s apart.
FAST = ResendPolicy(first_s=0.1, max_s=0.4, rate_hz=200.0)


@pytest.fixture(scope="module")
def dialect(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    return generate_dialect(tmp_path_factory.mktemp("mavgen"))


def airframe_sealer() -> Sealer:
    """Only today's and tomorrow's day keys, as an airframe holds them."""
    today = datetime.now(UTC).date()
    keys = {
        (AIRFRAME, day): derive_day_key(MASTER, AIRFRAME, day)
        for day in (today, today + timedelta(days=1))
    }
    return Sealer(AIRFRAME, DayKeys(keys=keys), lambda: datetime.now(UTC))


def odd_ones_twice(arrival: Arrival, copy: int) -> Answer:
    """Even detections are acknowledged at once; odd ones get a decoy first, then HELD or
    DUPLICATE when they come again (both mean "stop")."""
    if arrival.detection_id % 2 == 0:
        return "ack"
    if copy == 1:
        return "decoy"
    return "duplicate" if arrival.detection_id % 4 == 1 else "ack"


def cut_after_ten_for_fifteen(peer: AckPeer) -> bool:
    """The link drops everything from the 10th detection on, until 15 have been lost."""
    return len(peer.arrivals) >= 10 and len(peer.lost) < 15


@pytest.mark.anyio
@pytest.mark.parametrize("mode", ["plain", "signed", "tunnel"])
async def test_every_detection_arrives_through_a_cut_and_decoys_and_the_store_empties(
    dialect: ModuleType, mode: str
) -> None:
    sim = SimulatedAirframe(
        SYSID, PROFILE, resend=FAST, signing_key=SIGNING_KEY if mode == "signed" else None
    )
    sealer = airframe_sealer() if mode == "tunnel" else None
    with anyio.fail_after(15):
        async with (
            AckPeer.bound(
                dialect,
                answer=odd_ones_twice,
                cut=cut_after_ten_for_fifteen,
                master=MASTER if mode == "tunnel" else None,
                airframe_ids={SYSID: AIRFRAME},
                signing_key=SIGNING_KEY if mode == "signed" else None,
            ) as peer,
            anyio.create_task_group() as tg,
        ):
            tg.start_soon(peer.serve)
            run = partial(sim.run_udp, duration_s=2.0, speed=4.0, sealer=sealer, linger_s=10)
            await run("127.0.0.1", peer.port)
            tg.cancel_scope.cancel()
    sent = sim.resend.counts.sent
    assert sent == 41  # 2 s of sim time at 20 Hz, both ends included
    assert {a.detection_id for a in peer.arrivals} == set(range(1, sent + 1))
    assert len(peer.lost) == 15
    assert set(peer.lost) <= peer.identities()  # each detection cut away came again
    for identity in peer.identities():
        copies = peer.copies(identity)
        assert len({c.body for c in copies}) == 1  # a re-send is the same detection
        if identity[1] % 2 == 1:
            assert len(copies) >= 2  # the decoy did not stop it
    assert all(a.is_signed == (mode == "signed") for a in peer.arrivals)
    assert len(sim.resend) == 0
    counts = sim.resend.counts
    assert counts.acknowledged == sent
    assert counts.resent >= 15 + sent // 2
    assert counts.dropped == 0
    assert peer.rejected == 0
    if mode == "plain":  # the decoy was for another sysid: read, and ignored
        assert counts.acks_ignored == (sent + 1) // 2
    if mode == "tunnel":  # the decoy was unsealed: refused before it was parsed
        assert sim.link.uplink_rejected == (sent + 1) // 2


@pytest.mark.anyio
async def test_the_airframe_flies_on_while_nothing_listens_then_delivers_everything(
    dialect: ModuleType,
) -> None:
    """Nobody at the port for 2 s (the gateway down): sends are refused and counted, the
    detections are held; a ground station binds the port and everything arrives."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    sim = SimulatedAirframe(SYSID, SimProfile(detection_hz=10.0), resend=FAST)
    landed = anyio.Event()

    async def fly(*, task_status: anyio.abc.TaskStatus[None]) -> None:
        # Lingers after its 3 s until the ground station has acknowledged everything.
        await sim.run_udp("127.0.0.1", port, duration_s=3.0, linger_s=10, task_status=task_status)
        landed.set()

    with anyio.fail_after(15):
        async with anyio.create_task_group() as tg:
            await tg.start(fly)
            await anyio.sleep(2.0)  # the outage the test is about, not a synchronisation
            held_while_down = len(sim.resend)
            refused_while_down = sim.link.refused
            async with AckPeer.bound(dialect, port) as peer:
                tg.start_soon(peer.serve)
                await landed.wait()
                tg.cancel_scope.cancel()
    assert held_while_down >= 18  # ~20 detections sent into the void, none acknowledged
    assert refused_while_down > 0
    assert {a.detection_id for a in peer.arrivals} == set(range(1, 32))
    assert sim.resend.counts.acknowledged == 31
    assert sim.resend.counts.dropped == 0


@pytest.mark.anyio
async def test_a_long_outage_drains_at_the_capped_rate_and_a_full_store_drops_the_oldest(
    dialect: ModuleType,
) -> None:
    capped = ResendPolicy(first_s=0.05, max_s=0.05, rate_hz=40.0, capacity=25)
    sim = SimulatedAirframe(SYSID, SimProfile(detection_hz=50.0), resend=capped)
    with anyio.fail_after(15):
        async with (
            AckPeer.bound(dialect, cut=lambda p: len(p.arrivals) >= 1 and len(p.lost) < 50) as peer,
            anyio.create_task_group() as tg,
        ):
            tg.start_soon(peer.serve)
            start = anyio.current_time()
            await sim.run_udp("127.0.0.1", peer.port, duration_s=1.2, speed=1.0, linger_s=10)
            elapsed = anyio.current_time() - start
            tg.cancel_scope.cancel()
    counts = sim.resend.counts
    assert counts.sent == 61
    assert counts.dropped > 0  # 50 lost in a row, room for 25: the oldest went
    assert counts.acknowledged + counts.dropped == counts.sent
    assert len(sim.resend) == 0
    # The backlog left at no more than 40 re-sends a second (plus the one that starts it).
    assert counts.resent <= 40 * elapsed + 1
    delivered = {a.detection_id for a in peer.arrivals}
    assert len(delivered) == counts.sent - counts.dropped
    assert max(delivered) == counts.sent  # the newest were kept


@pytest.mark.anyio
async def test_hostile_uplink_datagrams_are_counted_and_skipped(dialect: ModuleType) -> None:
    """Oversize, garbage and truncated datagrams on the uplink: the airframe reads on."""
    sim = SimulatedAirframe(SYSID, PROFILE, resend=FAST)
    first_arrival, landed = anyio.Event(), anyio.Event()

    def ack_after_the_first(arrival: Arrival, copy: int) -> Answer:
        first_arrival.set()
        return "none" if arrival.detection_id == 1 and copy == 1 else "ack"

    async def fly(port: int, *, task_status: anyio.abc.TaskStatus[None]) -> None:
        await sim.run_udp(
            "127.0.0.1", port, duration_s=1.0, speed=2.0, linger_s=10, task_status=task_status
        )
        landed.set()

    ack = dialect.MAVLink_fischer_detection_ack_message(1, 1, SYSID, 1, 0)
    frame = bytes(ack.pack(dialect.MAVLink(None, 255, 190)))
    hostile = [b"\xfd" * 9000, b"\x00" * 64, frame[:-3], b"\xfd\xff" + frame[2:]]
    with anyio.fail_after(15):
        async with (
            AckPeer.bound(dialect, answer=ack_after_the_first) as peer,
            anyio.create_task_group() as tg,
        ):
            tg.start_soon(peer.serve)
            await tg.start(fly, peer.port)
            await first_arrival.wait()
            assert peer.address is not None
            for datagram in hostile:
                await peer.sock.sendto(datagram, *peer.address)
            await landed.wait()
            tg.cancel_scope.cancel()
    assert sim.link.uplink_rejected == 1  # the oversize one; the rest parsed to nothing
    assert sim.resend.counts.acknowledged == sim.resend.counts.sent == 21
    assert len(sim.resend) == 0
    assert {a.detection_id for a in peer.arrivals} == set(range(1, 22))
