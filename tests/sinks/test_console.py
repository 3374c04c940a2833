"""The console sink: readable lines, unknowns shown as '-', no fix said plainly."""

from __future__ import annotations

import contextlib
import io
import os
import threading
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import anyio
import pytest
from pydantic import ValidationError

from gateway.errors import TransientSinkError
from gateway.events import (
    BlueForce,
    Detection,
    Event,
    EventKind,
    Extension,
    LinkState,
    Position,
    Sensor,
    Telemetry,
    Track,
    event_adapter,
)
from gateway.testing import eventually
from sinks.console import ConsoleSink, ConsoleSinkConfig, describe

pytestmark = pytest.mark.anyio

T0 = datetime(2026, 11, 22, 12, 0, 1, 234000, tzinfo=UTC)
HERE = Position(lat_deg=65.8252, lon_deg=21.6886, alt_msl_m=250.0)


async def render(*events: Event, fmt: str = "text") -> list[str]:
    out = io.StringIO()
    config = ConsoleSinkConfig.model_validate({"format": fmt})
    sink = ConsoleSink("c", config, stream=out)
    with anyio.fail_after(5):
        await sink.open()
        await sink.send(list(events))
        await sink.aclose()
    text = out.getvalue()
    assert text.endswith("\n")
    return text.split("\n")[:-1]


class TestText:
    """One line per event, in the text format."""

    async def test_telemetry_with_a_position(self) -> None:
        (line,) = await render(
            Telemetry(
                event_id="1",
                airframe="F26E-001",
                time=T0,
                position=HERE,
                heading_deg=90.0,
                groundspeed_mps=22.0,
                battery_pct=87.0,
                active_link="sdr",
            )
        )
        assert line == (
            "12:00:01.234Z telemetry  F26E-001 65.82520,21.68860 alt 250.0 m MSL hdg 90° "
            "gs 22.0 m/s batt 87% link sdr"
        )

    async def test_telemetry_without_a_position_says_no_fix_and_shows_dashes(self) -> None:
        (line,) = await render(Telemetry(event_id="1", airframe="A", time=T0))
        assert line == "12:00:01.234Z telemetry  A no fix hdg - gs - batt - link -"

    async def test_zero_is_shown_as_zero_and_unknown_altitude_as_dash(self) -> None:
        (line,) = await render(
            Telemetry(
                event_id="1",
                airframe="A",
                time=T0,
                position=Position(lat_deg=0.0, lon_deg=0.0),
                heading_deg=0.0,
                groundspeed_mps=0.0,
                battery_pct=0.0,
            )
        )
        assert line.endswith("A 0.00000,0.00000 alt - MSL hdg 0° gs 0.0 m/s batt 0% link -")

    async def test_time_is_shown_in_utc_whatever_the_zone_of_the_event(self) -> None:
        local = T0.astimezone(timezone(timedelta(hours=2)))
        (line,) = await render(Telemetry(event_id="1", airframe="A", time=local))
        assert line.startswith("12:00:01.234Z ")

    async def test_link_state(self) -> None:
        (line,) = await render(
            LinkState(
                event_id="1",
                airframe="A",
                time=T0,
                link="sdr",
                is_up=False,
                is_active=False,
                loss_pct=2.5,
                reason="sdr not heard for 3.0 s",
            )
        )
        assert line == "12:00:01.234Z link_state A sdr DOWN loss 2.5% (sdr not heard for 3.0 s)"

    async def test_detection_without_subtype(self) -> None:
        (line,) = await render(
            Detection(
                event_id="1",
                airframe="F26E-001",
                time=T0,
                sensor=Sensor.IR,
                object_class="vehicle",
                confidence=0.87,
                position=HERE,
                sigma_h_m=12.0,
            )
        )
        assert line == (
            "12:00:01.234Z detection  F26E-001 ir vehicle - conf 0.87"
            " at 65.82520,21.68860 alt 250.0 m MSL ±12 m"
        )

    async def test_track_and_blue_force(self) -> None:
        track, blue = await render(
            Track(
                event_id="1",
                track_id="T-7",
                time=T0,
                object_class="vehicle",
                subtype="truck",
                confidence=0.9,
                position=HERE,
                cep50_m=10.0,
                cep90_m=25.0,
                first_seen=T0,
                last_seen=T0,
                hostility="hostile",
            ),
            BlueForce(event_id="2", uid="ANDROID-1", time=T0, position=HERE, source="cot"),
        )
        assert track == (
            "12:00:01.234Z track      T-7 updated vehicle truck hostile conf 0.90"
            " at 65.82520,21.68860 alt 250.0 m MSL cep50 10 m"
        )
        assert blue == (
            '12:00:01.234Z blue_force uid "ANDROID-1" - at 65.82520,21.68860 alt 250.0 m MSL'
            " via cot"
        )

    def test_a_callsign_is_shown_safe_and_marked_by_provenance(self) -> None:
        blue = BlueForce(
            event_id="2",
            uid="ANDROID-RED",
            time=T0,
            position=HERE,
            source="cot",
            source_name="atak-mesh",
            callsign="WEAPONS FREE\u202e - ENGAGE AUTHORISED BY BDE",
        )
        assert describe(blue) == (
            '12:00:01.234Z blue_force uid "ANDROID-RED" "WEAPONS FREE - ENGAGE AUTHORI..."'
            " (unauthenticated CoT callsign, source atak-mesh)"
            " at 65.82520,21.68860 alt 250.0 m MSL via cot"
        )

    def test_an_extension_is_named_by_its_type_and_publisher(self) -> None:
        event = Extension(
            event_id="w-1", type="acme.weather", time=T0, publisher="wx", data={"x": 1}
        )
        assert describe(event) == "12:00:01.234Z extension  acme.weather from wx w-1"

    def test_describe_is_the_text_format(self) -> None:
        event = Telemetry(event_id="1", airframe="A", time=T0)
        assert describe(event) == "12:00:01.234Z telemetry  A no fix hdg - gs - batt - link -"


class TestJson:
    """The json format writes each event as it reads back."""

    async def test_lines_parse_back_to_the_events(self) -> None:
        events: list[Event] = [
            Telemetry(event_id="1", airframe="A", time=T0),
            Telemetry(event_id="2", airframe="B", time=T0, position=HERE),
        ]
        lines = await render(*events, fmt="json")
        assert [event_adapter.validate_json(line) for line in lines] == events


class TestSink:
    """Config, streams and a console that does not take the write."""

    def test_kinds_default_to_every_kind_and_can_be_narrowed(self) -> None:
        assert ConsoleSink("c", ConsoleSinkConfig()).kinds == frozenset(EventKind)
        narrowed = ConsoleSinkConfig.model_validate({"kinds": ["telemetry", "link_state"]})
        assert ConsoleSink("c", narrowed).kinds == {EventKind.TELEMETRY, EventKind.LINK_STATE}
        with pytest.raises(ValidationError):
            ConsoleSinkConfig.model_validate({"kinds": []})
        with pytest.raises(ValidationError):
            ConsoleSinkConfig.model_validate({"format": "xml"})

    async def test_default_stream_is_stdout(self, capsys: pytest.CaptureFixture[str]) -> None:
        sink = ConsoleSink("c", ConsoleSinkConfig())
        with anyio.fail_after(5):
            await sink.send([Telemetry(event_id="1", airframe="A", time=T0)])
        assert capsys.readouterr().out == (
            "12:00:01.234Z telemetry  A no fix hdg - gs - batt - link -\n"
        )

    async def test_an_empty_batch_writes_nothing(self) -> None:
        out = io.StringIO()
        with anyio.fail_after(5):
            await ConsoleSink("c", ConsoleSinkConfig(), stream=out).send([])
        assert out.getvalue() == ""

    async def test_a_broken_pipe_is_a_transient_error_naming_the_sink(self) -> None:
        read_fd, write_fd = os.pipe()
        os.close(read_fd)
        with os.fdopen(write_fd, "w") as out:
            sink = ConsoleSink("c", ConsoleSinkConfig(), stream=out)
            with anyio.fail_after(5), pytest.raises(TransientSinkError) as caught:
                await sink.send([Telemetry(event_id="1", airframe="A", time=T0)])
            assert caught.value.sink == "c"
            assert str(caught.value) == "sink c: cannot write to the console: Broken pipe"
            with contextlib.suppress(BrokenPipeError):
                out.close()  # the buffered line cannot be flushed either

    async def test_a_stuck_console_fails_fast_instead_of_piling_up_threads(self) -> None:
        entered, release = threading.Event(), threading.Event()

        class StuckStream(io.StringIO):
            def write(self, text: str) -> int:
                entered.set()
                release.wait(10)
                return super().write(text)

        out = StuckStream()
        sink = ConsoleSink("c", ConsoleSinkConfig(), stream=out)
        event = Telemetry(event_id="1", airframe="A", time=T0)
        try:
            with anyio.fail_after(5):
                async with anyio.create_task_group() as tg:
                    tg.start_soon(sink.send, [event])
                    await anyio.to_thread.run_sync(entered.wait)
                    tg.cancel_scope.cancel()  # the runner's send deadline: the write is abandoned
                with pytest.raises(TransientSinkError, match=r"^sink c: .* still blocked"):
                    await sink.send([event])
        finally:
            release.set()
        with anyio.fail_after(5):
            await eventually(lambda: not sink._writes_in_flight)
            await sink.send([event])
        assert out.getvalue().count("\n") == 2


@pytest.mark.anyio
class TestOutput:
    """``output`` keeps the events apart from the gateway's logs (which go to stderr)."""

    async def test_a_file_output_is_appended_to_and_closed(self, tmp_path: Path) -> None:
        path = tmp_path / "events.txt"
        path.write_text("earlier\n")
        sink = ConsoleSink("c", ConsoleSinkConfig.model_validate({"output": str(path)}))
        with anyio.fail_after(5):
            await sink.open()
            await sink.send([Telemetry(event_id="1", airframe="A", time=T0)])
            await sink.aclose()
        assert path.read_text() == (
            "earlier\n12:00:01.234Z telemetry  A no fix hdg - gs - batt - link -\n"
        )

    async def test_stderr_output(self, capsys: pytest.CaptureFixture[str]) -> None:
        sink = ConsoleSink("c", ConsoleSinkConfig(output="stderr"))
        with anyio.fail_after(5):
            await sink.open()
            await sink.send([Telemetry(event_id="1", airframe="A", time=T0)])
        captured = capsys.readouterr()
        assert (captured.out, captured.err.count("telemetry")) == ("", 1)

    async def test_a_file_that_cannot_be_opened_is_a_transient_error(self, tmp_path: Path) -> None:
        config = ConsoleSinkConfig.model_validate({"output": str(tmp_path / "no" / "x.txt")})
        with anyio.fail_after(5), pytest.raises(TransientSinkError, match="sink c: cannot open"):
            await ConsoleSink("c", config).open()
