"""FISCHER_DETECTION and FISCHER_DETECTION_ACK: our message classes against mavgen's, and
detections through the gateway."""

from __future__ import annotations

from datetime import UTC, datetime
from types import ModuleType

import anyio
import pytest
from ack_peer import generate_dialect
from pydantic import ValidationError
from pymavlink.dialects.v20 import ardupilotmega as apm
from test_ingest import make_ingest

from gateway.app import Gateway
from gateway.config import Config
from gateway.events import Detection, Event, Position
from gateway.fleet.dialect import (
    FISCHER_DETECTION_ACK_CRC_EXTRA,
    FISCHER_DETECTION_ACK_RESULT_DUPLICATE,
    FISCHER_DETECTION_ACK_RESULT_HELD,
    FISCHER_DETECTION_CRC_EXTRA,
    FischerDetectionAck,
    fischer_detection,
    fischer_detection_ack,
)
from gateway.sim.airframe import SimProfile, SimulatedAirframe
from gateway.testing import MemorySink, eventually


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """The dialect module mavgen makes from gateway/fleet/fischer_dialect.xml: the oracle."""
    return generate_dialect(tmp_path_factory.mktemp("mavgen"))


ARGS = (1_763_800_000_000_000, 7, 658_352_000, 216_886_000, 150.5, 8.0, 1, 1, 91)


def test_crc_extra_and_bytes_match_mavgen(generated: ModuleType) -> None:
    assert generated.MAVLink_fischer_detection_message.crc_extra == FISCHER_DETECTION_CRC_EXTRA
    theirs = generated.MAVLink(None, srcSystem=1, srcComponent=1)
    ours = apm.MAVLink(None, srcSystem=1, srcComponent=1)
    expected = bytes(theirs.fischer_detection_encode(*ARGS, b"T-72").pack(theirs))
    assert fischer_detection(*ARGS, subtype="T-72").pack(ours) == expected
    assert len(expected) == 48


def test_frame_size_is_an_extension_crc_extra_and_old_frames_unchanged(
    generated: ModuleType,
) -> None:
    """An extension is outside CRC_EXTRA: an old sender's frames (no frame_size, sent as 0
    and cut by MAVLink 2's truncation) are byte for byte what they were."""
    theirs = generated.MAVLink(None, srcSystem=1, srcComponent=1)
    ours = apm.MAVLink(None, srcSystem=1, srcComponent=1)
    cls = generated.MAVLink_fischer_detection_message
    assert cls.crc_extra == FISCHER_DETECTION_CRC_EXTRA == 20
    assert cls.fieldnames[-2:] == ["subtype", "frame_size"]
    expected = bytes(theirs.fischer_detection_encode(*ARGS, b"T-72", 4).pack(theirs))
    assert fischer_detection(*ARGS, subtype="T-72", frame_size=4).pack(ours) == expected
    assert len(expected) == 12 + 32 + 16 + 1  # base, subtype, size: nothing truncated
    (msg,) = generated.MAVLink(None).parse_buffer(expected)
    assert msg.frame_size == 4
    old = fischer_detection(*ARGS, subtype="T-72").pack(apm.MAVLink(None, 1, 1))
    (back,) = apm.MAVLink(None).parse_buffer(old)
    assert back.frame_size == 0


def test_mavgen_parser_decodes_our_frame(generated: ModuleType) -> None:
    frame = fischer_detection(*ARGS, subtype="T-72").pack(apm.MAVLink(None, 1, 1))
    (msg,) = generated.MAVLink(None).parse_buffer(frame)
    assert (msg.detection_id, msg.lat, msg.class_id, msg.subtype) == (7, 658_352_000, 1, "T-72")


ACK_ARGS = (1_763_800_000_000_000, 4_000_000_007, 12, 1)


@pytest.mark.parametrize(
    "result", [FISCHER_DETECTION_ACK_RESULT_HELD, FISCHER_DETECTION_ACK_RESULT_DUPLICATE]
)
def test_ack_crc_extra_and_bytes_match_mavgen(generated: ModuleType, result: int) -> None:
    """Both results, including HELD (0), whose trailing zero MAVLink 2 truncates."""
    ack_class = generated.MAVLink_fischer_detection_ack_message
    assert ack_class.crc_extra == FISCHER_DETECTION_ACK_CRC_EXTRA
    assert ack_class.id == FischerDetectionAck.id
    assert ack_class.unpacker.format == FischerDetectionAck.unpacker.format
    theirs = generated.MAVLink(None, srcSystem=255, srcComponent=190)
    ours = apm.MAVLink(None, srcSystem=255, srcComponent=190)
    expected = bytes(theirs.fischer_detection_ack_encode(*ACK_ARGS, result).pack(theirs))
    assert fischer_detection_ack(*ACK_ARGS, result=result).pack(ours) == expected
    assert len(expected) == 12 + 15 - (1 if result == 0 else 0)


def test_mavgen_parser_decodes_our_ack_and_ours_decodes_theirs(generated: ModuleType) -> None:
    ours = apm.MAVLink(None, srcSystem=255, srcComponent=190)
    frame = fischer_detection_ack(*ACK_ARGS, result=FISCHER_DETECTION_ACK_RESULT_DUPLICATE).pack(
        ours
    )
    (msg,) = generated.MAVLink(None).parse_buffer(frame)
    assert msg.get_type() == "FISCHER_DETECTION_ACK"
    assert (msg.time_usec, msg.detection_id, msg.target_system, msg.target_component) == ACK_ARGS
    assert msg.result == FISCHER_DETECTION_ACK_RESULT_DUPLICATE
    theirs = generated.MAVLink(None, srcSystem=255, srcComponent=190)
    held = bytes(theirs.fischer_detection_ack_encode(*ACK_ARGS, 0).pack(theirs))
    (back,) = apm.MAVLink(None).parse_buffer(held)
    assert isinstance(back, FischerDetectionAck)
    assert (back.time_usec, back.detection_id, back.target_system, back.result) == (
        ACK_ARGS[0],
        ACK_ARGS[1],
        12,
        FISCHER_DETECTION_ACK_RESULT_HELD,
    )


def test_detection_becomes_a_durable_event() -> None:
    ingest, events, _ = make_ingest(1)
    now_us = int(datetime(2026, 11, 22, 12, 0, tzinfo=UTC).timestamp() * 1e6)
    args = (now_us - 2_000_000, *ARGS[1:])
    ingest.on_data("l", "p", fischer_detection(*args, subtype="T-72").pack(apm.MAVLink(None, 1, 1)))
    (detection,) = [e for e in events if isinstance(e, Detection)]
    assert (detection.object_class, detection.subtype, detection.sensor.value) == (
        "tank",
        "T-72",
        "ir",
    )
    assert detection.confidence == pytest.approx(0.91)
    assert detection.position.lat_deg == pytest.approx(65.8352)
    assert detection.time == datetime(2026, 11, 22, 11, 59, 58, tzinfo=UTC)


@pytest.mark.parametrize("alt", [3e38, -3e38, float("nan"), float("inf"), 150_000.0, -20_000.0])
def test_an_impossible_altitude_is_unknown_not_a_place(alt: float) -> None:
    """A link's float may hold anything: the detection keeps its place, not a 3e38 m height."""
    ingest, events, _ = make_ingest(1)
    args = (ARGS[0], ARGS[1], ARGS[2], ARGS[3], alt, *ARGS[5:])
    ingest.on_data("l", "p", fischer_detection(*args).pack(apm.MAVLink(None, 1, 1)))
    (detection,) = [e for e in events if isinstance(e, Detection)]
    assert detection.position.alt_msl_m is None
    assert detection.position.lat_deg == pytest.approx(65.8352)


def test_an_altitude_out_of_range_is_refused_by_name() -> None:
    with pytest.raises(ValidationError, match="alt_msl_m"):
        Position(lat_deg=60.0, lon_deg=18.0, alt_msl_m=3e38)
    with pytest.raises(ValidationError, match="alt_hae_m"):
        Position(lat_deg=60.0, lon_deg=18.0, alt_hae_m=float("nan"))


@pytest.mark.parametrize(("sent", "carried"), [(0, None), (1, 1), (12, 12), (255, 255)])
def test_frame_size_is_carried_into_the_detection_none_when_unknown(
    sent: int, carried: int | None
) -> None:
    ingest, events, _ = make_ingest(1)
    frame = fischer_detection(*ARGS, frame_size=sent).pack(apm.MAVLink(None, 1, 1))
    ingest.on_data("l", "p", frame)
    (detection,) = [e for e in events if isinstance(e, Detection)]
    assert detection.frame_size == carried
    assert Detection.model_validate(detection.model_dump()) == detection


def test_a_frame_size_out_of_range_is_refused_by_name() -> None:
    """A Detection from elsewhere (another node's, over NATS) is validated."""
    ingest, events, _ = make_ingest(1)
    ingest.on_data("l", "p", fischer_detection(*ARGS).pack(apm.MAVLink(None, 1, 1)))
    (detection,) = [e for e in events if isinstance(e, Detection)]
    for bad in (0, 256):
        with pytest.raises(ValidationError, match="frame_size"):
            Detection.model_validate({**detection.model_dump(), "frame_size": bad})


def test_impossible_detection_is_rejected_and_counted() -> None:
    ingest, events, inst = make_ingest(1)
    bad = (ARGS[0], 8, 0, 0, *ARGS[4:])  # 0,0: no position
    ingest.on_data("l", "p", fischer_detection(*bad).pack(apm.MAVLink(None, 1, 1)))
    assert not [e for e in events if isinstance(e, Detection)]
    assert inst.link_rejected.labels("l", "malformed").value == 1


@pytest.mark.anyio
async def test_simulated_detections_reach_a_sink_every_one() -> None:
    config = Config.model_validate(
        {
            "health": {"enabled": False},
            "airframes": [
                {
                    "id": "F26E-001",
                    "sysid": 1,
                    "links": [{"uri": "udp://127.0.0.1:0", "security": "unsecured"}],
                }
            ],
            "sinks": [{"name": "mem", "type": "memory"}],
            "routes": [{"sinks": ["mem"], "kinds": ["detection"]}],
        }
    )
    mem = MemorySink("mem")
    gateway = Gateway(config, sinks={"mem": mem})
    sim = SimulatedAirframe(1, SimProfile(detection_hz=5.0))
    with anyio.fail_after(15):
        async with anyio.create_task_group() as tg:
            await tg.start(gateway.run)
            port = next(iter(gateway.fleet.links.values())).local_port  # type: ignore[attr-defined]
            await sim.run_udp("127.0.0.1", port, duration_s=1.0, speed=5.0)
            await eventually(lambda: len(mem.events) >= 5)
            gateway.shutdown()
    events: list[Event] = mem.events
    assert [e.event_id.split("-")[3] for e in events] == [str(n) for n in range(1, len(events) + 1)]
    assert {e.object_class for e in events if isinstance(e, Detection)} == {"tank", "uav"}
    # Each simulated detection is the only one of its sensor frame, and says so.
    assert {e.frame_size for e in events if isinstance(e, Detection)} == {1}
