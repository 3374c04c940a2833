"""The JSONL archive: lines read back as the same events, rotation, pruning, errors, recovery."""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from uuid import uuid4

import anyio
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from structlog.testing import capture_logs

from gateway.errors import TransientSinkError
from gateway.events import (
    ALT_MAX_M,
    ALT_MIN_M,
    BlueForce,
    Detection,
    Event,
    EventKind,
    LinkState,
    Position,
    Sensor,
    Telemetry,
    Track,
    event_adapter,
)
from sinks.jsonl import JsonlSink, JsonlSinkConfig

pytestmark = pytest.mark.anyio

T0 = datetime(2026, 11, 22, 12, tzinfo=UTC)
#: 2027-01-15T08:00:00Z, the injected clock's start.
EPOCH_S = 1_800_000_000.0
HERE = Position(lat_deg=65.8252, lon_deg=21.6886, alt_msl_m=250.0)


def tel(n: int) -> Telemetry:
    return Telemetry(
        event_id=f"t-{n}",
        airframe="F26E-001",
        time=T0,
        position=Position(lat_deg=65.8 + n * 1e-6, lon_deg=21.7, alt_msl_m=250.0),
        battery_pct=None,
    )


def every_kind() -> list[Event]:
    return [
        tel(0),
        LinkState(
            event_id="l-1",
            airframe="F26E-001",
            time=T0,
            link="sdr",
            is_up=True,
            is_active=True,
            loss_pct=0.5,
            reason="heard",
        ),
        Detection(
            event_id="d-1",
            airframe="F26E-001",
            time=T0,
            sensor=Sensor.IR,
            object_class="vehicle",
            subtype="Pansarbandvagn 302 \u2028 ä",  # a line separator JSON leaves raw
            confidence=0.8,
            position=HERE,
            sigma_h_m=12.0,
        ),
        Track(
            event_id="k-1",
            track_id="T-1",
            time=T0,
            object_class="vehicle",
            confidence=0.9,
            position=HERE,
            cep50_m=10.0,
            cep90_m=25.0,
            detection_ids=("d-1",),
            airframes=("F26E-001",),
            first_seen=T0,
            last_seen=T0,
        ),
        BlueForce(event_id="b-1", uid="ANDROID-1", time=T0, position=HERE, source="cot"),
    ]


class Clock:
    """Wall-clock seconds the test moves by hand."""

    def __init__(self) -> None:
        self.now = EPOCH_S

    def __call__(self) -> float:
        return self.now


async def read(path: Path) -> list[Event]:
    lines = (await anyio.Path(path).read_text(encoding="utf-8")).split("\n")
    assert lines[-1] == "", "the file ends with a newline"
    return [event_adapter.validate_json(line) for line in lines[:-1]]


async def write(sink: JsonlSink, *batches: Sequence[Event]) -> None:
    await sink.open()
    try:
        for batch in batches:
            await sink.send(batch)
    finally:
        await sink.aclose()


async def names(directory: Path) -> list[str]:
    return sorted([p.name async for p in anyio.Path(directory).iterdir()])


async def rotated_files(directory: Path) -> list[Path]:
    return [directory / n for n in await names(directory) if n.startswith("archive-")]


async def size(path: Path) -> int:
    return (await anyio.Path(path).stat()).st_size


class TestWrite:
    """Events are appended one per line and read back equal."""

    async def test_every_kind_reads_back_equal_in_order(self, tmp_path: Path) -> None:
        path = tmp_path / "a" / "b" / "archive.jsonl"  # directories created on open
        events = every_kind() + [tel(n) for n in range(1, 10)]
        with anyio.fail_after(5):
            await write(JsonlSink("arc", JsonlSinkConfig(path=path)), events[:4], events[4:])
            assert await read(path) == events

    async def test_a_reopened_archive_is_appended_to(self, tmp_path: Path) -> None:
        path = tmp_path / "archive.jsonl"
        with anyio.fail_after(5):
            await write(JsonlSink("arc", JsonlSinkConfig(path=path)), [tel(1)])
            await write(JsonlSink("arc", JsonlSinkConfig(path=path)), [tel(2)])
            assert await read(path) == [tel(1), tel(2)]

    async def test_relative_path_is_resolved_against_the_cwd_at_open(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        sink = JsonlSink("arc", JsonlSinkConfig(path=Path("rel/archive.jsonl")))
        monkeypatch.chdir(tmp_path)
        with anyio.fail_after(5):
            await sink.open()
        monkeypatch.chdir(tmp_path / "rel")  # a later cwd change does not move the archive
        with anyio.fail_after(5):
            await sink.send([tel(1)])
            await sink.aclose()
            assert await read(tmp_path / "rel" / "archive.jsonl") == [tel(1)]
        assert not await anyio.Path(tmp_path / "rel" / "rel").exists()

    async def test_one_worker_thread_call_per_batch(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        calls: list[str] = []
        real = anyio.to_thread.run_sync

        async def counting(func: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
            calls.append(getattr(func, "__name__", "?"))
            return await real(func, *args, **kwargs)

        monkeypatch.setattr(anyio.to_thread, "run_sync", counting)
        sink = JsonlSink("arc", JsonlSinkConfig(path=tmp_path / "archive.jsonl", fsync=True))
        with anyio.fail_after(5):
            await sink.open()
            for start in (0, 50, 100):
                await sink.send([tel(n) for n in range(start, start + 50)])
        assert calls == ["_open_and_prune", "_write", "_write", "_write"]
        with anyio.fail_after(5):
            await sink.aclose()

    async def test_fsync_option_syncs_once_per_batch(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        synced: list[int] = []
        real = os.fsync

        def counting_fsync(fd: int) -> None:
            synced.append(fd)
            real(fd)

        monkeypatch.setattr(os, "fsync", counting_fsync)
        path = tmp_path / "archive.jsonl"
        with anyio.fail_after(5):
            await write(JsonlSink("plain", JsonlSinkConfig(path=path)), [tel(1)], [tel(2)])
        assert synced == []
        with anyio.fail_after(5):
            await write(
                JsonlSink("synced", JsonlSinkConfig(path=path, fsync=True)), [tel(3)], [tel(4)]
            )
            assert await read(path) == [tel(1), tel(2), tel(3), tel(4)]
        assert len(synced) == 2

    async def test_an_empty_batch_writes_nothing(self, tmp_path: Path) -> None:
        path = tmp_path / "archive.jsonl"
        with anyio.fail_after(5):
            await write(JsonlSink("arc", JsonlSinkConfig(path=path)), [])
            assert await size(path) == 0


class TestConfig:
    """The options and their defaults."""

    def test_defaults(self) -> None:
        config = JsonlSinkConfig(path=Path("a.jsonl"))
        assert config.max_bytes == 100 * 1024 * 1024
        assert config.max_age_s == 86_400
        assert config.keep == 30
        assert config.fsync is False
        assert JsonlSink("arc", config).kinds == frozenset(EventKind)

    def test_kinds_can_be_narrowed_but_not_emptied(self) -> None:
        config = JsonlSinkConfig.model_validate({"path": "a.jsonl", "kinds": ["detection"]})
        assert JsonlSink("arc", config).kinds == {EventKind.DETECTION}
        with pytest.raises(ValidationError, match="kinds"):
            JsonlSinkConfig.model_validate({"path": "a.jsonl", "kinds": []})

    def test_class_declares_its_config_model(self) -> None:
        assert JsonlSink.config_model is JsonlSinkConfig


class TestRotation:
    """Rotation by size and by age, names after the open time, pruning to ``keep``."""

    async def test_size_rotation_keeps_files_under_max_bytes_and_loses_nothing(
        self, tmp_path: Path
    ) -> None:
        path = tmp_path / "archive.jsonl"
        clock = Clock()
        sink = JsonlSink("arc", JsonlSinkConfig(path=path, max_bytes=1024, keep=100), clock=clock)
        events: list[Event] = [tel(n) for n in range(40)]
        with anyio.fail_after(5):
            await sink.open()
            for event in events:
                clock.now += 1
                await sink.send([event])
            await sink.aclose()
            rotated = await rotated_files(tmp_path)
            assert len(rotated) > 2
            assert all([await size(p) <= 1024 for p in [*rotated, path]])
            read_back = [e for p in [*rotated, path] for e in await read(p)]
        assert read_back == events

    async def test_size_rotation_prunes_to_the_newest_keep(self, tmp_path: Path) -> None:
        path = tmp_path / "archive.jsonl"
        clock = Clock()
        sink = JsonlSink("arc", JsonlSinkConfig(path=path, max_bytes=1024, keep=2), clock=clock)
        with anyio.fail_after(5):
            await sink.open()
            for n in range(40):
                clock.now += 1
                await sink.send([tel(n)])
            await sink.aclose()
            rotated = await rotated_files(tmp_path)
            assert len(rotated) == 2
            kept = [e for p in [*rotated, path] for e in await read(p)]
        assert kept == [tel(n) for n in range(40)][-len(kept) :]
        assert len(kept) < 40

    async def test_age_rotation_is_measured_from_open_on_the_injected_clock(
        self, tmp_path: Path
    ) -> None:
        path = tmp_path / "archive.jsonl"
        clock = Clock()
        sink = JsonlSink("arc", JsonlSinkConfig(path=path, max_age_s=60), clock=clock)
        with anyio.fail_after(5):
            await sink.open()
            await sink.send([tel(1)])
            clock.now += 59
            await sink.send([tel(2)])  # 59 s after open: not yet
            assert await names(tmp_path) == ["archive.jsonl"]
            clock.now += 1
            await sink.send([tel(3)])  # 60 s after open: rotated first
            await sink.aclose()
            assert await names(tmp_path) == ["archive-20270115T080000Z.jsonl", "archive.jsonl"]
            assert await read(tmp_path / "archive-20270115T080000Z.jsonl") == [tel(1), tel(2)]
            assert await read(path) == [tel(3)]

    async def test_an_empty_file_is_not_rotated_however_old(self, tmp_path: Path) -> None:
        path = tmp_path / "archive.jsonl"
        clock = Clock()
        sink = JsonlSink("arc", JsonlSinkConfig(path=path, max_age_s=60), clock=clock)
        with anyio.fail_after(5):
            await sink.open()
            clock.now += 3600
            await sink.send([tel(1)])
            await sink.aclose()
            assert await names(tmp_path) == ["archive.jsonl"]

    async def test_a_taken_name_gets_a_counter(self, tmp_path: Path) -> None:
        path = tmp_path / "archive.jsonl"
        clock = Clock()  # never moves: every rotation has the same stamp
        sink = JsonlSink("arc", JsonlSinkConfig(path=path, max_bytes=1024), clock=clock)
        big = [tel(n) for n in range(5)]  # about 900 bytes: each batch forces a rotation
        with anyio.fail_after(5):
            await write(sink, big, big, big, big)
            assert await names(tmp_path) == [
                "archive-20270115T080000Z-1.jsonl",
                "archive-20270115T080000Z-2.jsonl",
                "archive-20270115T080000Z.jsonl",
                "archive.jsonl",
            ]

    async def test_pruning_orders_by_stamp_and_counter_and_spares_other_files(
        self, tmp_path: Path
    ) -> None:
        path = tmp_path / "archive.jsonl"
        with anyio.fail_after(5):
            for name in [
                "archive-20261122T120000Z.jsonl",
                "archive-20261122T120000Z-1.jsonl",
                "archive-20261122T120000Z-10.jsonl",
                "archive-20261122T120000Z-2.jsonl",
                "archive-20261123T000000Z.jsonl",
                "archive-notes.jsonl",  # not ours: kept
                "other-20261122T120000Z.jsonl",  # another archive's: kept
            ]:
                await anyio.Path(tmp_path / name).write_text("{}\n")
            await write(JsonlSink("arc", JsonlSinkConfig(path=path, keep=2)), [tel(1)])
            assert await names(tmp_path) == [
                "archive-20261122T120000Z-10.jsonl",
                "archive-20261123T000000Z.jsonl",
                "archive-notes.jsonl",
                "archive.jsonl",
                "other-20261122T120000Z.jsonl",
            ]

    async def test_keep_zero_keeps_no_rotated_file(self, tmp_path: Path) -> None:
        path = tmp_path / "archive.jsonl"
        clock = Clock()
        sink = JsonlSink("arc", JsonlSinkConfig(path=path, max_age_s=1, keep=0), clock=clock)
        with anyio.fail_after(5):
            await sink.open()
            for n in range(3):
                await sink.send([tel(n)])
                clock.now += 1
            await sink.aclose()
            assert await names(tmp_path) == ["archive.jsonl"]
            assert await read(path) == [tel(2)]

    async def test_rotation_is_logged_without_payload(self, tmp_path: Path) -> None:
        path = tmp_path / "archive.jsonl"
        clock = Clock()
        sink = JsonlSink("arc", JsonlSinkConfig(path=path, max_age_s=1, keep=1), clock=clock)
        with capture_logs() as logs, anyio.fail_after(5):
            await sink.open()
            for n in range(3):
                await sink.send([tel(n)])
                clock.now += 1
            await sink.aclose()
        rotations = [entry for entry in logs if entry["event"] == "archive_rotated"]
        assert rotations == [
            {
                "event": "archive_rotated",
                "log_level": "info",
                "sink": "arc",
                "path": str(path),
                "rotated_to": "archive-20270115T080000Z.jsonl",
                "pruned": 0,
            },
            {
                "event": "archive_rotated",
                "log_level": "info",
                "sink": "arc",
                "path": str(path),
                "rotated_to": "archive-20270115T080001Z.jsonl",
                "pruned": 1,
            },
        ]
        assert "F26E-001" not in repr(logs)


class TestErrors:
    """Every OSError is a TransientSinkError that names the sink and the path."""

    async def test_a_path_that_is_a_directory(self, tmp_path: Path) -> None:
        await anyio.Path(tmp_path / "dir.jsonl").mkdir()
        sink = JsonlSink("arc", JsonlSinkConfig(path=tmp_path / "dir.jsonl"))
        with anyio.fail_after(5), pytest.raises(TransientSinkError) as caught:
            await sink.open()
        assert caught.value.sink == "arc"
        assert str(caught.value) == (
            f"sink arc: cannot open {tmp_path / 'dir.jsonl'}: Is a directory"
        )
        with anyio.fail_after(5):
            await sink.aclose()  # safe after a failed open

    async def test_a_parent_that_is_a_file(self, tmp_path: Path) -> None:
        await anyio.Path(tmp_path / "file").write_text("")
        sink = JsonlSink("arc", JsonlSinkConfig(path=tmp_path / "file" / "archive.jsonl"))
        with anyio.fail_after(5), pytest.raises(TransientSinkError, match=r"^sink arc: .*file"):
            await sink.open()

    @pytest.mark.skipif(os.geteuid() == 0, reason="root ignores directory permissions")
    async def test_a_read_only_directory(self, tmp_path: Path) -> None:
        directory = tmp_path / "ro"
        await anyio.Path(directory).mkdir(mode=0o500)
        try:
            sink = JsonlSink("arc", JsonlSinkConfig(path=directory / "archive.jsonl"))
            with anyio.fail_after(5), pytest.raises(TransientSinkError) as caught:
                await sink.open()
        finally:
            await anyio.Path(directory).chmod(0o700)
        assert caught.value.sink == "arc"
        assert "Permission denied" in str(caught.value)

    @pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs Linux /dev/full")
    async def test_a_full_disk_is_transient(self) -> None:
        sink = JsonlSink("arc", JsonlSinkConfig(path=Path("/dev/full")))
        with anyio.fail_after(5):
            await sink.open()
            with pytest.raises(TransientSinkError) as caught:
                await sink.send([tel(1)])
        assert str(caught.value) == (
            "sink arc: cannot write /dev/full: No space left on device (disk full)"
        )
        assert isinstance(caught.value.__cause__, OSError)
        assert caught.value.__cause__.errno == errno.ENOSPC
        with anyio.fail_after(5):
            await sink.aclose()

    async def test_a_failed_write_leaves_no_half_batch_and_the_retry_lands_once(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        path = tmp_path / "archive.jsonl"
        sink = JsonlSink("arc", JsonlSinkConfig(path=path))
        real_write = os.write
        failures: list[int] = []

        def half_then_fail(fd: int, data: Any) -> int:
            if failures and fd == sink._fd:
                real_write(fd, bytes(data[: len(data) // 2]))
                raise OSError(failures.pop(), "No space left on device")
            return real_write(fd, data)

        monkeypatch.setattr(os, "write", half_then_fail)
        with anyio.fail_after(5):
            await sink.open()
            await sink.send([tel(1)])
            failures.append(errno.ENOSPC)
            with pytest.raises(TransientSinkError, match="disk full"):
                await sink.send([tel(2), tel(3)])
            await sink.send([tel(2), tel(3)])  # the runner's retry
            await sink.aclose()
            assert await read(path) == [tel(1), tel(2), tel(3)]


class TestRecovery:
    """A line left half-written by a crash does not spoil the lines after it."""

    async def test_a_partial_last_line_is_ended_before_the_next_event(self, tmp_path: Path) -> None:
        path = tmp_path / "archive.jsonl"
        await anyio.Path(path).write_text(tel(1).model_dump_json() + "\n" + '{"kind": "telem')
        with capture_logs() as logs, anyio.fail_after(5):
            await write(JsonlSink("arc", JsonlSinkConfig(path=path)), [tel(2)])
            lines = (await anyio.Path(path).read_text()).split("\n")
        assert lines == [tel(1).model_dump_json(), '{"kind": "telem', tel(2).model_dump_json(), ""]
        assert event_adapter.validate_json(lines[2]) == tel(2)
        assert [e["event"] for e in logs if e["log_level"] == "warning"] == [
            "archive_partial_line_ended"
        ]

    async def test_a_complete_file_gets_no_extra_newline(self, tmp_path: Path) -> None:
        path = tmp_path / "archive.jsonl"
        await anyio.Path(path).write_text(tel(1).model_dump_json() + "\n")
        with anyio.fail_after(5):
            await write(JsonlSink("arc", JsonlSinkConfig(path=path)), [tel(2)])
            assert await read(path) == [tel(1), tel(2)]


finite = st.floats(allow_nan=False, allow_infinity=False)
maybe_finite = st.none() | finite


@settings(
    max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    event=st.builds(
        Telemetry,
        event_id=st.text(min_size=1, max_size=20),
        airframe=st.text(min_size=1, max_size=20),
        time=st.datetimes(timezones=st.just(UTC)),
        position=st.none()
        | st.builds(
            Position,
            lat_deg=st.floats(-90, 90),
            lon_deg=st.floats(-180, 180),
            alt_msl_m=st.none() | st.floats(ALT_MIN_M, ALT_MAX_M),
            alt_hae_m=st.none() | st.floats(ALT_MIN_M, ALT_MAX_M),
        ),
        alt_agl_m=maybe_finite,
        heading_deg=maybe_finite,
        groundspeed_mps=maybe_finite,
        battery_pct=st.none() | st.floats(0, 100),
        satellites_visible=st.none() | st.integers(0, 64),
        is_armed=st.none() | st.booleans(),
        ew_mode=st.none() | st.text(max_size=10),
    )
)
async def test_any_telemetry_round_trips(tmp_path: Path, event: Telemetry) -> None:
    """Whatever the text or the float, the line parses back to an equal event."""
    path = tmp_path / f"{uuid4().hex}.jsonl"
    with anyio.fail_after(5):
        await write(JsonlSink("arc", JsonlSinkConfig(path=path)), [event])
        assert await read(path) == [event]
