"""The .tlog reader and replayer: corpus agreement with pymavlink, resync, truncation, UDP."""

from __future__ import annotations

import re
import struct
import tracemalloc
from collections import Counter
from pathlib import Path
from typing import Any

import anyio
import anyio.abc
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink import mavutil
from pymavlink.dialects.v10 import ardupilotmega as apm1
from pymavlink.dialects.v20 import ardupilotmega as apm2

from gateway.fleet.tlog import TlogRecord, TlogStats, parse_udp_target, read_tlog, replay_udp
from gateway.sim.airframe import SimulatedAirframe
from gateway.testing import fuzz_examples

T0_US = 1_763_800_000_000_000  # 2025-11-22
DAY_US = 86_400 * 1_000_000


def corpus_dir() -> Path:
    """``<repo root>/../shared/corpus``, or skip the test when it is absent."""
    root = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
    corpus = root.parent / "shared" / "corpus"
    if not corpus.is_dir():
        pytest.skip(f"shared corpus absent: {corpus}")
    return corpus


def sample_frames() -> list[bytes]:
    """MAVLink 2 frames from the simulator, a MAVLink 1 frame and a signed MAVLink 2 frame."""
    frames = SimulatedAirframe(1).frames_at(0.0)
    v1 = apm1.MAVLink(None, srcSystem=2, srcComponent=1)
    frames.append(bytes(v1.heartbeat_encode(1, 3, 0, 0, 4).pack(v1)))
    signer = apm2.MAVLink(None, srcSystem=3, srcComponent=1)
    signer.signing.secret_key = bytes(range(32))
    signer.signing.link_id = 1
    signer.signing.timestamp = 1
    signer.signing.sign_outgoing = True
    frames.append(bytes(signer.statustext_encode(6, b"signed").pack(signer)))
    return frames


def sample_records(count: int = 3) -> list[TlogRecord]:
    frames = sample_frames() * count
    return [TlogRecord(T0_US + i * 20_000, frame) for i, frame in enumerate(frames)]


def encode(records: list[TlogRecord]) -> list[bytes]:
    return [struct.pack(">Q", r.timestamp_us) + r.frame for r in records]


def read_all(path: Path) -> tuple[list[TlogRecord], TlogStats]:
    stats = TlogStats()
    return list(read_tlog(path, stats)), stats


def decode_counts(frames: list[bytes]) -> Counter[str]:
    parser = apm2.MAVLink(None)
    parser.robust_parsing = True
    counts: Counter[str] = Counter()
    for frame in frames:
        counts.update(m.get_type() for m in parser.parse_buffer(frame) or [])
    return counts


class TestReadTlog:
    """``read_tlog`` yields every intact record and counts what it skips."""

    def test_sample_frames_cover_v1_v2_and_signed(self) -> None:
        frames = sample_frames()
        assert {f[0] for f in frames} == {0xFD, 0xFE}
        assert any(f[0] == 0xFD and f[2] & 0x01 for f in frames)

    @pytest.mark.corpus
    def test_corpus_frames_per_type_equal_pymavlink(self) -> None:
        path = corpus_dir() / "mavlink" / "arducopter_hw_ground_small.tlog"
        if not path.is_file():
            pytest.skip(f"corpus file absent: {path}")
        records, stats = read_all(path)
        reference: Counter[str] = Counter()
        connection: Any = mavutil.mavlink_connection(str(path), robust_parsing=True)
        try:
            while (msg := connection.recv_msg()) is not None:
                reference[msg.get_type()] += 1
        finally:
            connection.close()
        assert decode_counts([r.frame for r in records]) == reference
        assert "BAD_DATA" not in reference
        versions = Counter(r.frame[0] for r in records)
        assert versions[0xFD] > 0
        assert versions[0xFE] > 0
        assert (stats.records, stats.skipped_bytes, stats.truncated_bytes) == (len(records), 0, 0)
        assert sum(8 + len(r.frame) for r in records) == path.stat().st_size

    def test_round_trip_of_v1_v2_and_signed_frames(self, tmp_path: Path) -> None:
        records = sample_records()
        path = tmp_path / "a.tlog"
        path.write_bytes(b"".join(encode(records)))
        assert read_all(path) == (records, TlogStats(records=len(records)))

    @pytest.mark.parametrize("where", [0, 1, 10, -1])
    @pytest.mark.parametrize(
        "garbage", [b"\x00\xfd\xfe" * 7 + b"noise", b"\xfd" * 300, bytes(range(256)) * 3]
    )
    def test_garbage_is_skipped_and_counted(
        self, tmp_path: Path, where: int, garbage: bytes
    ) -> None:
        records = sample_records()
        chunks = encode(records)
        chunks.insert(where, garbage)
        path = tmp_path / "a.tlog"
        path.write_bytes(b"".join(chunks))
        got, stats = read_all(path)
        assert got == records
        assert stats.skipped_bytes == len(garbage)

    def test_a_record_without_magic_is_dropped_and_the_rest_recovered(self, tmp_path: Path) -> None:
        records = sample_records()
        chunks = encode(records)
        chunks[5] = chunks[5][:8] + b"\x55" + chunks[5][9:]
        path = tmp_path / "a.tlog"
        path.write_bytes(b"".join(chunks))
        got, stats = read_all(path)
        assert got == records[:5] + records[6:]
        assert stats.skipped_bytes == len(chunks[5])

    def test_clock_jumps_between_intact_records_are_followed(self, tmp_path: Path) -> None:
        frames = sample_frames()
        stamps = [T0_US, T0_US + 3 * DAY_US, 5_000_000, 5_020_000, T0_US, T0_US + 1]
        records = [TlogRecord(ts, frames[i % len(frames)]) for i, ts in enumerate(stamps)]
        path = tmp_path / "a.tlog"
        path.write_bytes(b"".join(encode(records)))
        assert read_all(path) == (records, TlogStats(records=len(records)))

    @pytest.mark.parametrize("keep", [1, 7, 8, 9, 11, 20, -1])
    def test_a_truncated_tail_is_dropped(self, tmp_path: Path, keep: int) -> None:
        records = sample_records()
        chunks = encode(records)
        cut = chunks[-1][:keep]
        path = tmp_path / "a.tlog"
        path.write_bytes(b"".join(chunks[:-1]) + cut)
        got, stats = read_all(path)
        assert got == records[:-1]
        assert (stats.skipped_bytes, stats.truncated_bytes) == (0, len(cut))

    def test_an_empty_file_has_no_records(self, tmp_path: Path) -> None:
        path = tmp_path / "empty.tlog"
        path.write_bytes(b"")
        assert read_all(path) == ([], TlogStats())

    def test_memory_stays_bounded_on_a_large_file(self, tmp_path: Path) -> None:
        chunk = b"".join(encode(sample_records(20)))
        path = tmp_path / "big.tlog"
        path.write_bytes(chunk * (3_000_000 // len(chunk)))
        tracemalloc.start()
        try:
            count = sum(1 for _ in read_tlog(path))
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert count == len(sample_records(20)) * (3_000_000 // len(chunk))
        assert peak < 1_000_000

    @settings(max_examples=fuzz_examples(300), deadline=None)
    @given(data=st.binary(max_size=4096))
    def test_arbitrary_bytes_never_raise_and_every_byte_is_accounted(
        self, tmp_path_factory: pytest.TempPathFactory, data: bytes
    ) -> None:
        path = tmp_path_factory.mktemp("fuzz") / "x.tlog"
        path.write_bytes(data)
        records, stats = read_all(path)
        used = sum(8 + len(r.frame) for r in records)
        assert used + stats.skipped_bytes + stats.truncated_bytes == len(data)
        for r in records:
            assert r.frame[0] in (0xFD, 0xFE)
            header, extra = (10, 2 + 13 * (r.frame[2] & 1)) if r.frame[0] == 0xFD else (6, 2)
            assert len(r.frame) == header + r.frame[1] + extra

    @settings(max_examples=fuzz_examples(200), deadline=None)
    @given(
        spec=st.lists(
            st.tuples(
                st.integers(0, 5_000_000),
                st.sampled_from([(0xFE, 0), (0xFD, 0), (0xFD, 1)]),
                st.binary(min_size=0, max_size=255),
            ),
            max_size=30,
        )
    )
    def test_well_formed_records_round_trip(
        self, tmp_path_factory: pytest.TempPathFactory, spec: list[tuple[int, Any, bytes]]
    ) -> None:
        records, ts = [], T0_US
        for gap_us, (magic, signed), payload in spec:
            ts += gap_us
            header = bytes([magic, len(payload)])
            header += bytes([signed, 0, 0, 1, 1, 0, 0, 0]) if magic == 0xFD else bytes(4)
            frame = header + payload + b"\x12\x34" + b"\x5a" * 13 * signed
            records.append(TlogRecord(ts, frame))
        path = tmp_path_factory.mktemp("prop") / "x.tlog"
        path.write_bytes(b"".join(encode(records)))
        assert read_all(path) == (records, TlogStats(records=len(records)))


class TestParseUdpTarget:
    """The CLI's ``--to udp://HOST:PORT``."""

    @pytest.mark.parametrize(
        ("text", "expected"),
        [
            ("udp://127.0.0.1:14550", ("127.0.0.1", 14550)),
            ("udp://[::1]:14551", ("::1", 14551)),
            ("udp://gateway.local:1/", ("gateway.local", 1)),
        ],
    )
    def test_accepts_udp_urls(self, text: str, expected: tuple[str, int]) -> None:
        assert parse_udp_target(text) == expected

    @pytest.mark.parametrize(
        "text",
        [
            "tcp://127.0.0.1:14550",
            "127.0.0.1:14550",
            "udp://127.0.0.1",
            "udp://:14550",
            "udp://h:0",
            "udp://h:70000",
            "udp://h:port",
            "udp://h:1/path",
            "udp://h:1?x=1",
            "udp://user@h:1",
            "",
        ],
    )
    def test_rejects_anything_else_naming_the_text(self, text: str) -> None:
        with pytest.raises(ValueError, match=re.escape(repr(text))):
            parse_udp_target(text)


async def receive(sock: anyio.abc.UDPSocket, count: int) -> list[bytes]:
    return [(await sock.receive())[0] for _ in range(count)]


async def replay_and_receive(path: Path, count: int, **kwargs: Any) -> tuple[int, list[bytes]]:
    """Replay ``path`` to a loopback socket bound here and receive ``count`` datagrams."""
    got: list[bytes] = []
    async with await anyio.create_udp_socket(local_host="127.0.0.1") as sock:
        port = sock.extra(anyio.abc.SocketAttribute.local_port)

        async def collect() -> None:
            got.extend(await receive(sock, count))

        async with anyio.create_task_group() as tg:
            tg.start_soon(collect)
            sent = await replay_udp(path, "127.0.0.1", port, **kwargs)
    return sent, got


@pytest.mark.anyio
class TestReplayUdp:
    """``replay_udp`` sends every frame, byte-identical, paced or as fast as possible."""

    @pytest.mark.corpus
    async def test_corpus_replay_delivers_every_frame_byte_identical(self) -> None:
        path = corpus_dir() / "mavlink" / "arducopter_hw_ground_small.tlog"
        if not path.is_file():
            pytest.skip(f"corpus file absent: {path}")
        frames = [r.frame for r in read_tlog(path)]
        with anyio.fail_after(10):
            sent, got = await replay_and_receive(path, len(frames), speed=None)
        assert sent == len(frames)
        assert got == frames

    async def test_pacing_follows_recorded_time_and_skips_clock_jumps(self, tmp_path: Path) -> None:
        frames = sample_frames()
        stamps = [T0_US + i * 100_000 for i in range(10)]
        stamps[5:] = [ts + 2 * DAY_US for ts in stamps[5:]]  # a jump, not waited for
        path = tmp_path / "a.tlog"
        path.write_bytes(b"".join(encode([TlogRecord(ts, frames[0]) for ts in stamps])))
        with anyio.fail_after(5):
            start = anyio.current_time()
            sent, got = await replay_and_receive(path, 10, speed=3.0)
            elapsed = anyio.current_time() - start
        assert (sent, got) == (10, [frames[0]] * 10)
        # Eight 100 ms gaps remain once the jump is dropped: 0.8 s / 3.
        assert elapsed >= 0.8 / 3

    async def test_seal_wraps_each_frame(self, tmp_path: Path) -> None:
        records = sample_records(1)
        path = tmp_path / "a.tlog"
        path.write_bytes(b"".join(encode(records)))
        with anyio.fail_after(5):
            sent, got = await replay_and_receive(
                path, len(records), speed=None, seal=lambda f: b"S" + f
            )
        assert sent == len(records)
        assert got == [b"S" + r.frame for r in records]

    async def test_a_missing_file_fails_before_started(self, tmp_path: Path) -> None:
        with anyio.fail_after(5), pytest.RaisesGroup(FileNotFoundError):
            async with anyio.create_task_group() as tg:
                await tg.start(replay_udp, tmp_path / "missing.tlog", "127.0.0.1", 9)

    @pytest.mark.parametrize("speed", [0.0, -1.0, float("inf"), float("nan")])
    async def test_rejects_a_bad_speed(self, tmp_path: Path, speed: float) -> None:
        with pytest.raises(ValueError, match="speed"):
            await replay_udp(tmp_path / "a.tlog", "127.0.0.1", 9, speed=speed)
