"""The JSONL archive: lines read back as the same events, rotation, pruning, recovery."""

from __future__ import annotations

import os
from datetime import UTC, datetime
from pathlib import Path

import anyio
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gateway.errors import TransientSinkError
from gateway.events import Event, Position, Telemetry, event_adapter
from sinks.jsonl import JsonlSink, JsonlSinkConfig

T0 = datetime(2026, 11, 22, 12, tzinfo=UTC)


def tel(n: int) -> Telemetry:
    return Telemetry(
        event_id=f"t-{n}",
        airframe="F26E-001",
        time=T0,
        position=Position(lat_deg=65.8 + n * 1e-6, lon_deg=21.7, alt_msl_m=250.0),
        battery_pct=None,
    )


class Clock:
    def __init__(self) -> None:
        self.now = 1_800_000_000.0

    def __call__(self) -> float:
        return self.now


def write(sink: JsonlSink, *batches: list[Event]) -> None:
    async def go() -> None:
        with anyio.fail_after(5):
            await sink.open()
            for batch in batches:
                await sink.send(batch)
            await sink.aclose()

    anyio.run(go)


def read(path: Path) -> list[Event]:
    lines = path.read_text(encoding="utf-8").split("\n")
    assert lines[-1] == ""
    return [event_adapter.validate_json(line) for line in lines[:-1]]


def test_events_read_back_equal(tmp_path: Path) -> None:
    path = tmp_path / "a" / "archive.jsonl"
    events: list[Event] = [tel(n) for n in range(10)]
    write(JsonlSink("arc", JsonlSinkConfig(path=path)), events[:4], events[4:])
    assert read(path) == events


def test_rotation_by_size_and_pruning_keeps_newest(tmp_path: Path) -> None:
    path = tmp_path / "archive.jsonl"
    clock = Clock()
    sink = JsonlSink("arc", JsonlSinkConfig(path=path, max_bytes=1024, keep=2), clock=clock)

    async def go() -> None:
        await sink.open()
        for n in range(40):
            clock.now += 1
            await sink.send([tel(n)])
        await sink.aclose()

    anyio.run(go)
    rotated = sorted(tmp_path.glob("archive-*.jsonl"))
    assert len(rotated) == 2
    assert all(p.stat().st_size <= 1024 for p in [*rotated, path])
    assert read(path)[-1] == tel(39)


def test_rotation_by_age(tmp_path: Path) -> None:
    path = tmp_path / "archive.jsonl"
    clock = Clock()
    sink = JsonlSink("arc", JsonlSinkConfig(path=path, max_age_s=60), clock=clock)

    async def go() -> None:
        await sink.open()
        await sink.send([tel(1)])
        clock.now += 61
        await sink.send([tel(2)])
        await sink.aclose()

    anyio.run(go)
    (rotated,) = tmp_path.glob("archive-*.jsonl")
    assert read(rotated) == [tel(1)]
    assert read(path) == [tel(2)]
    assert rotated.name == "archive-20270115T080000Z.jsonl"


def test_partial_last_line_from_a_crash_is_terminated(tmp_path: Path) -> None:
    path = tmp_path / "archive.jsonl"
    path.write_text(tel(1).model_dump_json() + "\n" + '{"kind": "telem')
    write(JsonlSink("arc", JsonlSinkConfig(path=path)), [tel(2)])
    lines = path.read_text().splitlines()
    assert event_adapter.validate_json(lines[-1]) == tel(2)
    assert lines[1] == '{"kind": "telem'


def test_unwritable_path_is_a_transient_error_naming_the_sink(tmp_path: Path) -> None:
    (tmp_path / "dir.jsonl").mkdir()
    sink = JsonlSink("arc", JsonlSinkConfig(path=tmp_path / "dir.jsonl"))
    with pytest.raises(TransientSinkError, match=r"sink arc: cannot open .*dir\.jsonl"):
        anyio.run(sink.open)


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores directory permissions")
def test_read_only_directory_is_a_transient_error(tmp_path: Path) -> None:
    tmp_path.chmod(0o500)
    try:
        sink = JsonlSink("arc", JsonlSinkConfig(path=tmp_path / "x.jsonl"))
        with pytest.raises(TransientSinkError):
            anyio.run(sink.open)
    finally:
        tmp_path.chmod(0o700)


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(
    max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.builds(
        Telemetry,
        event_id=st.text(min_size=1, max_size=20),
        airframe=st.text(min_size=1, max_size=20),
        time=st.datetimes(timezones=st.just(UTC)),
        position=st.none()
        | st.builds(
            Position,
            lat_deg=st.floats(-90, 90),
            lon_deg=st.floats(-180, 180),
            alt_msl_m=st.none() | finite,
        ),
        groundspeed_mps=st.none() | finite,
        battery_pct=st.none() | st.floats(0, 100),
    )
)
def test_any_telemetry_round_trips(tmp_path: Path, event: Telemetry) -> None:
    path = tmp_path / "prop.jsonl"
    path.unlink(missing_ok=True)
    write(JsonlSink("arc", JsonlSinkConfig(path=path)), [event])
    assert read(path) == [event]
