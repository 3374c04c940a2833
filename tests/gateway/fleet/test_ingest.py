"""Ingest and normalise: bytes from links become the right Telemetry, bad bytes are counted."""

from __future__ import annotations

import random
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.config import AirframeConfig, LinkConfig
from gateway.events import Event, LinkState, Telemetry
from gateway.fleet.ingest import Ingest, LinkIntake
from gateway.fleet.tlog import read_tlog
from gateway.ops.instruments import Instruments
from gateway.testing import fuzz_examples

CORPUS = Path(__file__).resolve().parents[3].parent / "shared" / "corpus"
SMALL_TLOG = CORPUS / "mavlink" / "arducopter_hw_ground_small.tlog"
T0 = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)


def make_ingest(*sysids: int) -> tuple[Ingest, list[Event], Instruments]:
    events: list[Event] = []
    inst = Instruments()
    airframes = [
        AirframeConfig(
            id=f"AF-{s}",
            sysid=s,
            links=(LinkConfig(uri="udp://127.0.0.1:1", name="l", security="unsecured"),),
        )
        for s in sysids
    ]
    ingest = Ingest(airframes, events.append, inst, lambda: T0)
    ingest.register_link(LinkIntake("l", "unsecured", is_stream=False))
    return ingest, events, inst


def encoder(sysid: int, compid: int = 1) -> mav.MAVLink:
    m = mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    return m


def pack(m: mav.MAVLink, msg: mav.MAVLink_message) -> bytes:
    frame = bytes(msg.pack(m))
    m.seq = (m.seq + 1) % 256  # pack() does not advance it; send() would
    return frame


def gpi(m: mav.MAVLink, lat: int, lon: int, alt: int) -> bytes:
    return pack(m, m.global_position_int_encode(1000, lat, lon, alt, 5000, 100, -200, 30, 9000))


def telemetry_of(events: list[Event]) -> list[Telemetry]:
    return [e for e in events if isinstance(e, Telemetry)]


class TestNormalise:
    """MAVLink fields become SI-unit Telemetry fields, with unknowns as None."""

    def test_position_velocity_and_heading(self) -> None:
        ingest, events, _ = make_ingest(7)
        ingest.on_data("l", "p", gpi(encoder(7), 658252000, 216886000, 250500))
        (tel,) = telemetry_of(events)
        assert tel.airframe == "AF-7"
        assert tel.position is not None
        assert (tel.position.lat_deg, tel.position.lon_deg) == (65.8252, 21.6886)
        assert tel.position.alt_msl_m == 250.5
        assert tel.position.alt_rel_home_m == 5.0
        assert tel.velocity is not None
        assert (tel.velocity.north_mps, tel.velocity.east_mps) == (1.0, -2.0)
        assert tel.heading_deg == 90.0

    def test_gps_alt_ellipsoid_gives_height_above_ellipsoid(self) -> None:
        ingest, events, _ = make_ingest(7)
        m = encoder(7)
        gps = m.gps_raw_int_encode(
            0,
            3,
            658252000,
            216886000,
            250000,
            80,
            120,
            2200,
            9000,
            14,
            alt_ellipsoid=272000,
            h_acc=1500,
        )
        ingest.on_data("l", "p", bytes(gps.pack(m)))
        ingest.on_data("l", "p", gpi(m, 658252000, 216886000, 250000))
        tel = telemetry_of(events)[-1]
        assert tel.position is not None
        assert tel.position.alt_hae_m == pytest.approx(272.0)
        assert tel.h_acc_m == 1.5
        assert tel.satellites_visible == 14

    def test_a_position_off_the_globe_is_refused_and_counted_leaving_the_last_one(self) -> None:
        ingest, events, inst = make_ingest(7)
        m = encoder(7)
        ingest.on_data("l", "p", gpi(m, 658252000, 216886000, 250500))
        for lat, lon in ((900_000_001, 0), (0, -1_800_000_001), (2**31 - 1, 2**31 - 1)):
            ingest.on_data("l", "p", gpi(m, lat, lon, 250500))
        assert inst.link_ignored.labels("l", "handler_error").value == 3
        assert inst.link_frames.labels("l").value == 4
        tel = telemetry_of(events)
        assert len(tel) == 1  # nothing of the refused messages was merged
        ingest.on_data("l", "p", gpi(m, 900_000_000, -1_800_000_000, 250500))  # the edges
        last = telemetry_of(events)[-1].position
        assert last is not None
        assert (last.lat_deg, last.lon_deg) == (90.0, -180.0)

    def test_position_at_zero_zero_is_no_fix_not_null_island(self) -> None:
        ingest, events, _ = make_ingest(7)
        ingest.on_data("l", "p", gpi(encoder(7), 0, 0, 0))
        assert telemetry_of(events)[-1].position is None

    def test_heartbeat_from_companion_does_not_overwrite_vehicle(self) -> None:
        ingest, events, _ = make_ingest(7)
        m, companion = encoder(7, 1), encoder(7, 191)
        hb = m.heartbeat_encode(1, 3, 128 | 1, 15, 4)
        ingest.on_data("l", "p", bytes(hb.pack(m)))
        other = companion.heartbeat_encode(18, 8, 0, 0, 0)
        ingest.on_data("l", "p", bytes(other.pack(companion)))
        tel = telemetry_of(events)[-1]
        assert (tel.mav_type, tel.is_armed, tel.custom_mode) == (1, True, 15)

    def test_battery_unknowns_are_none(self) -> None:
        ingest, events, _ = make_ingest(7)
        m = encoder(7)
        status = m.sys_status_encode(0, 0, 0, 0, 65535, -1, -1, 0, 0, 0, 0, 0, 0)
        ingest.on_data("l", "p", bytes(status.pack(m)))
        tel = telemetry_of(events)[-1]
        assert (tel.battery_voltage_v, tel.battery_current_a, tel.battery_pct) == (None, None, None)


class TestLinkHealth:
    """Sequence gaps, unknown systems and link state changes."""

    def test_sequence_gaps_count_as_loss(self) -> None:
        ingest, _, _ = make_ingest(7)
        m = encoder(7)
        frames = [gpi(m, 600000000 + i, 200000000, 1000) for i in range(10)]
        for i, frame in enumerate(frames):
            if i not in (3, 4):
                ingest.on_data("l", "p", frame)
        (link,) = ingest.status()[0]["links"]  # type: ignore[misc]
        assert link["loss_pct"] == pytest.approx(20.0)

    def test_unknown_sysid_is_counted_not_fatal(self) -> None:
        ingest, events, inst = make_ingest(7)
        for _ in range(3):
            ingest.on_data("l", "p", gpi(encoder(99), 1, 1, 1))
        assert events == []
        assert inst.link_ignored.labels("l", "unknown_sysid").value == 3
        assert ingest.unknown_sysids == {99}

    def test_link_goes_up_on_first_frame_and_down_after_timeout(self) -> None:
        ingest, events, _ = make_ingest(7)
        ingest.on_data("l", "p", gpi(encoder(7), 1, 1, 1))
        up = [e for e in events if isinstance(e, LinkState)]
        assert [(e.is_up, e.is_active) for e in up] == [(True, True)]
        ingest.check_links(now_mono=time.monotonic() + 100)
        states = [e for e in events if isinstance(e, LinkState)]
        assert [(e.is_up, e.is_active) for e in states] == [(True, True), (False, False)]
        assert telemetry_of(events)[-1].active_link == "l"


class TestBadBytes:
    """Garbage, truncated frames and oversize datagrams are counted, never raised."""

    @settings(max_examples=fuzz_examples(300), deadline=None)
    @given(st.lists(st.binary(max_size=600), max_size=8))
    def test_arbitrary_bytes_never_raise(self, chunks: list[bytes]) -> None:
        ingest, _, inst = make_ingest(1)
        for chunk in chunks:
            ingest.on_data("l", "peer", chunk)
        assert inst.link_chunks.labels("l").value == len(chunks)

    @settings(max_examples=200, deadline=None)
    @given(st.integers(min_value=1, max_value=39), st.binary(max_size=40))
    def test_truncated_frame_then_good_frame_still_parses(self, cut: int, noise: bytes) -> None:
        ingest, events, _ = make_ingest(1)
        frame = gpi(encoder(1), 600000000, 200000000, 1000)
        # One datagram per frame, as on UDP: a truncated datagram must not eat the next one.
        ingest.on_data("l", "a", frame[:cut])
        ingest.on_data("l", "b", noise)
        ingest.on_data("l", "c", frame)
        assert telemetry_of(events)

    def test_oversize_datagram_is_rejected_and_counted(self) -> None:
        ingest, events, inst = make_ingest(1)
        ingest.on_data("l", "p", b"\xfd" * 5000)
        assert events == []
        assert inst.link_rejected.labels("l", "oversize").value == 1

    def test_corrupted_crc_is_counted_as_malformed(self) -> None:
        ingest, events, inst = make_ingest(1)
        frame = bytearray(gpi(encoder(1), 600000000, 200000000, 1000))
        frame[-1] ^= 0xFF
        ingest.on_data("l", "p", bytes(frame))
        ingest.on_data("l", "p", gpi(encoder(1), 600000001, 200000000, 1000))
        assert len(telemetry_of(events)) == 1
        assert inst.link_rejected.labels("l", "malformed").value >= 1


def pymavlink_positions(path: Path) -> Iterator[tuple[float, float, float]]:
    conn = mavutil.mavlink_connection(str(path), robust_parsing=True)
    while (msg := conn.recv_match(type="GLOBAL_POSITION_INT")) is not None:
        if msg.get_srcSystem() == 1:
            yield (msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0)
    conn.close()


@pytest.mark.corpus
def test_corpus_tlog_positions_equal_pymavlink_decode() -> None:
    """Every GLOBAL_POSITION_INT of a real mixed v1/v2, six-source log, as pymavlink reads it."""
    if not SMALL_TLOG.exists():
        pytest.skip("shared corpus absent")
    ingest, events, inst = make_ingest(1)
    for record in read_tlog(SMALL_TLOG):
        ingest.on_data("l", "tlog", record.frame)
    expected = list(pymavlink_positions(SMALL_TLOG))
    got = []
    last = None
    for tel in telemetry_of(events):
        pos = tel.position
        if pos is not None and (pos.lat_deg, pos.lon_deg, pos.alt_msl_m) != last:
            last = (pos.lat_deg, pos.lon_deg, pos.alt_msl_m)
            got.append(last)
    deduped = [p for i, p in enumerate(expected) if i == 0 or p != expected[i - 1]]
    assert len(expected) == 128
    assert got == deduped
    assert inst.link_ignored.labels("l", "unknown_sysid").value > 0  # the GCS, sysid 255


@pytest.mark.corpus
@pytest.mark.parametrize(
    "name",
    [
        "arducopter_hw_ground_small.tlog",
        "arducopter_hw_ground_companion.tlog",
        "ardusub_real_dive_small.tlog",
    ],
)
@pytest.mark.parametrize("drop", [0.0, 0.47])
def test_loss_ratio_of_real_logs_is_the_loss_of_the_autopilot_frames(
    name: str, drop: float
) -> None:
    """Real hardware logs mix components with unrelated sequences (companion, radio, camera).

    Lossless, they read 70-80 % loss when every component's gaps were summed; with 47 % of
    the datagrams really dropped the ratio must say about 0.47.
    """
    path = CORPUS / "mavlink" / name
    if not path.exists():
        pytest.skip("shared corpus absent")
    ingest, _events, _inst = make_ingest(1)
    rng = random.Random(7)
    for record in read_tlog(path):
        if rng.random() >= drop:
            ingest.on_data("l", "tlog", record.frame)
    (link,) = ingest.status()[0]["links"]  # type: ignore[misc]
    assert link["loss_pct"] / 100 == pytest.approx(drop, abs=0.02)


def test_a_failing_message_handler_costs_that_message_only() -> None:
    """session.on() is an extension point: its bug is counted, never raised into a link."""
    ingest, events, inst = make_ingest(1)
    session = ingest.sessions["AF-1"]

    def broken(_session: object, _label: str, _msg: object) -> None:
        raise KeyError("a bug in a handler")

    session.on("HEARTBEAT", broken)
    m = encoder(1)
    ingest.on_data("l", "peer", pack(m, m.heartbeat_encode(1, 3, 0, 0, 4)))
    ingest.on_data("l", "peer", gpi(m, 590000000, 180000000, 100000))
    ingest.flush()
    assert inst.link_ignored.labels("l", "handler_error").value == 1
    assert telemetry_of(events)  # the next message was handled as usual
