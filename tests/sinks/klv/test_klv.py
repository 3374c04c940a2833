"""The KLV sink: what it emits, read by independent decoders; UDP and MPEG-TS through ffmpeg."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import anyio
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from tools import skip_without

from gateway.errors import TransientSinkError
from gateway.events import Position, VideoFrameMetadata
from gateway.testing import fuzz_examples
from sinks.klv.ber import split_packets
from sinks.klv.imapb import Special
from sinks.klv.sink import KlvSink, KlvSinkConfig
from sinks.klv.st0601 import decode, resolution
from sinks.klv.uas import frame_packet, frame_values

stanag = pytest.importorskip("stanag4609.st0601")
klvdata = pytest.importorskip("klvdata")

T0 = datetime(2026, 11, 22, 10, 15, 30, 250000, tzinfo=UTC)
#: Tags klvdata 0.0.3 reads right (not IMAPB, not 2-byte tags, no error indicators).
KLVDATA_READS = frozenset(range(2, 66)) | {75, 90, 91}


def spec_checksum(packet: bytes) -> int:
    """ST 0601's 16-bit running sum, written apart from the codec (spec digest §2)."""
    total = 0
    for i, byte in enumerate(packet[:-2]):
        total += (byte << 8) if i % 2 == 0 else byte
    return total & 0xFFFF


def frame(i: int = 0, **changes: Any) -> VideoFrameMetadata:
    fields: dict[str, Any] = {
        "event_id": f"F26E-001-vfm-{i}",
        "airframe": "F26E-001",
        "time": T0 + timedelta(milliseconds=200 * i),
        "sensor_position": Position(
            lat_deg=58.410812, lon_deg=15.621403 + i * 1e-5, alt_msl_m=612.4, alt_hae_m=640.0
        ),
        "heading_deg": 87.5,
        "pitch_deg": -2.5,
        "roll_deg": 3.0,
        "airspeed_mps": 24.0,
        "groundspeed_mps": 23.0,
        "alt_agl_m": 520.0,
        "hfov_deg": 12.5,
        "vfov_deg": 7.0,
        "sensor_azimuth_deg": 45.0,
        "sensor_elevation_deg": -30.0,
        "sensor_roll_deg": 0.0,
        "frame_centre": Position(lat_deg=58.423917, lon_deg=15.650112, alt_msl_m=92.65),
        "frame_centre_source": "camera",
        "slant_range_m": 1250.0,
        "target_width_m": 274.0,
    }
    return VideoFrameMetadata(**(fields | changes))


def finite(low: float, high: float) -> st.SearchStrategy[float]:
    return st.floats(low, high, allow_nan=False, exclude_max=True)


positions = st.builds(
    Position,
    lat_deg=finite(-90, 90),
    lon_deg=finite(-180, 180),
    alt_msl_m=st.none() | finite(-900, 19_000),
    alt_hae_m=st.none() | finite(-900, 19_000),
)
frames = st.builds(
    VideoFrameMetadata,
    event_id=st.just("e"),
    airframe=st.sampled_from(["F26E-001", "F26E-042"]),
    time=st.datetimes(
        min_value=datetime(2000, 1, 1),  # noqa: DTZ001 - hypothesis adds the zone
        max_value=datetime(2100, 1, 1),  # noqa: DTZ001
        timezones=st.just(UTC),
    ),
    sensor_position=positions,
    heading_deg=st.none() | finite(0, 360),
    pitch_deg=st.none() | finite(-90, 90),
    roll_deg=st.none() | finite(-180, 180),
    airspeed_mps=st.none() | finite(0, 300),
    groundspeed_mps=st.none() | finite(0, 300),
    alt_agl_m=st.none() | finite(-900, 40_000),
    hfov_deg=st.none() | st.floats(0.1, 180),
    vfov_deg=st.none() | st.floats(0.1, 180),
    sensor_azimuth_deg=st.none() | finite(0, 360),
    sensor_elevation_deg=st.none() | finite(-180, 180),
    sensor_roll_deg=st.none() | finite(0, 360),
    frame_centre=st.none() | positions,
    is_off_earth=st.booleans(),
    slant_range_m=st.none() | finite(0, 5_000_000),
    target_width_m=st.none() | finite(0, 20_000),
)


def check_independent_decoders(packet: bytes) -> None:
    """stanag4609 and klvdata read ``packet`` as we do; the checksum is the spec's."""
    ours = decode(packet)
    assert spec_checksum(packet) == int.from_bytes(packet[-2:], "big")
    theirs = {f.definition.tag: f.value for f in stanag.decode_uas_local_set(packet).fields}
    assert theirs.pop(1) == spec_checksum(packet)
    assert set(theirs) == set(ours)
    for tag, value in ours.items():
        other = theirs[tag]
        if isinstance(value, Special):
            assert getattr(other, "value", None) in {"off_earth", "out_of_range", "reserved"}
        elif isinstance(value, float):
            assert float(other) == pytest.approx(value, abs=resolution(tag, 8) + 1e-9)
        else:
            assert other == value, tag
    if any(isinstance(v, Special) for v in ours.values()):
        return  # klvdata 0.0.3 raises ValueError on every error indicator (spec digest §7)
    (parsed,) = list(klvdata.StreamParser(packet))
    read = {key[0]: element.value for key, element in parsed.items.items()}
    for tag, value in ours.items():
        if tag not in KLVDATA_READS:
            continue
        got = getattr(read[tag], "value", read[tag])
        if isinstance(value, datetime):
            assert got.replace(tzinfo=UTC) == value
        elif isinstance(value, int | float):
            assert float(got) == pytest.approx(value, abs=resolution(tag) + 1e-9), tag
        else:
            assert got == value, tag


class TestPackets:
    def test_the_seed_example_values(self) -> None:
        values = decode(frame_packet(frame(), mission_id="FISCHER-26E-0042"))
        assert values[2] == T0
        assert (values[3], values[4], values[10]) == ("FISCHER-26E-0042", "F26E-001", "Fischer 26E")
        expected = {5: 87.5, 6: -2.5, 7: 3.0, 13: 58.410812, 14: 15.621403, 15: 612.4,
                    16: 12.5, 17: 7.0, 18: 45.0, 19: -30.0, 21: 1250.0, 22: 274.0,
                    23: 58.423917, 24: 15.650112, 25: 92.65, 75: 640.0, 113: 520.0}  # fmt: skip
        for tag, value in expected.items():
            assert values[tag] == pytest.approx(value, abs=resolution(tag)), tag
        assert (values[8], values[56], values[65]) == (24, 23, 19)

    def test_off_earth_and_out_of_range_send_the_indicators(self) -> None:
        event = frame(frame_centre=None, is_off_earth=True, pitch_deg=35.0, roll_deg=-70.0)
        values = decode(frame_packet(event))
        assert values[23] is values[24] is Special.ERROR
        assert values[6] is values[7] is Special.ERROR
        assert values[90] == pytest.approx(35.0, abs=resolution(90))
        assert values[91] == pytest.approx(-70.0, abs=resolution(91))
        check_independent_decoders(frame_packet(event))

    @settings(max_examples=fuzz_examples(60))
    @given(frames)
    def test_every_packet_we_emit_reads_the_same_in_stanag4609_and_klvdata(
        self, event: VideoFrameMetadata
    ) -> None:
        packet = frame_packet(event)
        check_independent_decoders(packet)
        assert set(decode(packet)) <= set(frame_values(event))
        got = decode(packet)
        assert got[13] == pytest.approx(event.sensor_position.lat_deg, abs=resolution(13))


def udp_receiver() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    return sock


async def receive(sock: socket.socket, count: int) -> list[bytes]:
    got: list[bytes] = []
    with anyio.fail_after(10):
        while len(got) < count:
            await anyio.wait_readable(sock)
            got.append(sock.recv(65_536))
    return got


@pytest.mark.anyio
async def test_udp_one_packet_per_datagram() -> None:
    with udp_receiver() as sock:
        port = sock.getsockname()[1]
        sink = KlvSink(
            "klv", KlvSinkConfig.model_validate({"udp": {"host": "127.0.0.1", "port": port}})
        )
        await sink.open()
        try:
            events = [frame(i) for i in range(5)]
            await sink.send(events)
        finally:
            await sink.aclose()
        got = await receive(sock, 5)
    assert got == [frame_packet(e) for e in events]
    for packet in got:
        check_independent_decoders(packet)


async def drain(sock: socket.socket, quiet_s: float = 0.5) -> list[bytes]:
    """Every datagram until none came for ``quiet_s`` (they were all sent before)."""
    got: list[bytes] = []
    while True:
        with anyio.move_on_after(quiet_s):
            await anyio.wait_readable(sock)
            got.append(sock.recv(65_536))
            continue
        return got


def test_options_need_a_destination() -> None:
    with pytest.raises(ValueError, match="give udp, mpegts or both"):
        KlvSinkConfig.model_validate({})


FFMPEG = shutil.which("ffmpeg")
FFPROBE = shutil.which("ffprobe")
needs_ffmpeg = skip_without("ffmpeg", "ffprobe")


def probe_streams(path: Path) -> list[tuple[str, str, str]]:
    """(type, codec, tag) of every stream ffprobe lists in ``path``."""
    assert FFPROBE is not None
    out = subprocess.run(
        [FFPROBE, "-v", "error", "-show_streams", "-of", "json", str(path)],
        check=True, capture_output=True, text=True, timeout=60,
    ).stdout  # fmt: skip
    return [
        (s["codec_type"], s["codec_name"], s.get("codec_tag_string", ""))
        for s in json.loads(out)["streams"]
    ]


def extract_klv(path: Path, tmp: Path) -> bytes:
    assert FFMPEG is not None
    out = tmp / "extracted.klv"
    subprocess.run(
        [FFMPEG, "-v", "error", "-y", "-i", str(path), "-map", "0:d:0", "-c", "copy",
         "-f", "data", str(out)],
        check=True, timeout=60,
    )  # fmt: skip
    return out.read_bytes()


async def sink_ts(events: list[VideoFrameMetadata]) -> list[bytes]:
    """The datagrams a KLV sink with a KLV-only ``mpegts`` destination sent for ``events``."""
    with udp_receiver() as sock:
        options = {"mpegts": {"host": "127.0.0.1", "port": sock.getsockname()[1]}}
        sink = KlvSink("klv", KlvSinkConfig.model_validate(options))
        await sink.open()
        try:
            await sink.send(events)
        finally:
            await sink.aclose()  # flushes the last partial datagram
        return await drain(sock)


@needs_ffmpeg
def test_mpegts_beside_test_video_through_ffmpeg(tmp_path: Path) -> None:
    """Our KLV-only TS over UDP, muxed by ffmpeg beside a test-source video, then extracted."""
    assert FFMPEG is not None
    events = [frame(i) for i in range(20)]
    datagrams = anyio.run(sink_ts, events)
    assert all(len(d) % 188 == 0 for d in datagrams)
    klv_ts = tmp_path / "klv.ts"
    klv_ts.write_bytes(b"".join(datagrams))
    assert probe_streams(klv_ts) == [("data", "klv", "KLVA")]
    av = tmp_path / "av.ts"
    video = "testsrc=size=160x120:rate=10:duration=4"
    subprocess.run(
        [FFMPEG, "-v", "error", "-y", "-f", "lavfi", "-i", video, "-i", str(klv_ts),
         "-map", "0:v", "-map", "1:d", "-c:v", "mpeg2video", "-c:d", "copy",
         "-f", "mpegts", str(av)],
        check=True, timeout=60,
    )  # fmt: skip
    assert [s[:2] for s in probe_streams(av)] == [("video", "mpeg2video"), ("data", "klv")]
    expected = b"".join(frame_packet(e) for e in events)
    assert extract_klv(av, tmp_path) == expected
    assert [decode(p)[2] for p in split_packets(expected)] == [e.time for e in events]


def test_video_needs_ffmpeg_on_the_path() -> None:
    options = {"mpegts": {"host": "127.0.0.1", "port": 9, "video": "in.ts", "ffmpeg": "no-such"}}
    with pytest.raises(ValueError, match="'no-such' is not on the PATH"):
        KlvSinkConfig.model_validate(options, context={"environment": True})
    KlvSinkConfig.model_validate(options)  # away from the node: not looked for


@needs_ffmpeg
@pytest.mark.anyio
async def test_an_ffmpeg_that_exits_is_reported_by_the_lifetime(tmp_path: Path) -> None:
    """A video ffmpeg cannot open: the sink's ``run`` raises, naming the sink and ffmpeg."""
    missing = str(tmp_path / "no-video.ts")
    options = {"mpegts": {"host": "127.0.0.1", "port": 9, "video": missing}}
    sink = KlvSink("klv-7", KlvSinkConfig.model_validate(options))
    await sink.open()
    try:
        with anyio.fail_after(30), pytest.raises(TransientSinkError) as caught:
            await sink.run(task_status=anyio.TASK_STATUS_IGNORED)
        with pytest.raises(TransientSinkError, match="ffmpeg is not running"):
            await sink.send([frame()])
    finally:
        await sink.aclose()
    message = str(caught.value)
    assert "sink klv-7: ffmpeg is not running" in message
    assert "no-video.ts" in message  # ffmpeg's own last line says what it could not open


def test_check_config_names_a_missing_ffmpeg_on_the_node_only(tmp_path: Path) -> None:
    """On the node it is an error with its key and line; ``--no-environment`` does not look."""
    config = tmp_path / "node.yaml"
    config.write_text(
        "airframes:\n"
        "  - {id: F26E-001, sysid: 1,\n"
        "     links: [{uri: 'udp://127.0.0.1:14550', security: unsecured}]}\n"
        "sinks:\n"
        "  - name: klv-001\n"
        "    type: klv\n"
        "    options:\n"
        "      mpegts: {host: 127.0.0.1, port: 5004, video: 'udp://0.0.0.0:5600'}\n"
    )
    env = {**os.environ, "PATH": str(tmp_path)}  # no ffmpeg there

    def check(*flags: str) -> subprocess.CompletedProcess[str]:
        command = [sys.executable, "-m", "gateway", "check-config", *flags, str(config)]
        return subprocess.run(command, capture_output=True, text=True, env=env, timeout=60)

    on_node = check()
    assert on_node.returncode == 2, on_node.stderr
    assert "node.yaml:8 sinks[0].options.mpegts: video needs ffmpeg" in on_node.stderr
    away = check("--no-environment")
    assert away.returncode == 0, away.stderr
