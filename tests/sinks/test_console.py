"""The console sink: readable lines, unknowns shown as '-', no fix said plainly."""

from __future__ import annotations

import io
import json
from datetime import UTC, datetime

import anyio

from gateway.events import LinkState, Position, Telemetry
from sinks.console import ConsoleSink, ConsoleSinkConfig

T0 = datetime(2026, 11, 22, 12, 0, 1, 234000, tzinfo=UTC)


def render(*events: Telemetry | LinkState, fmt: str = "text") -> list[str]:
    out = io.StringIO()
    sink = ConsoleSink("c", ConsoleSinkConfig(format=fmt), stream=out)  # type: ignore[arg-type]
    anyio.run(sink.send, list(events))
    return out.getvalue().splitlines()


def test_telemetry_line_with_position() -> None:
    (line,) = render(
        Telemetry(
            event_id="1",
            airframe="F26E-001",
            time=T0,
            position=Position(lat_deg=65.8252, lon_deg=21.6886, alt_msl_m=250.0),
            heading_deg=90.0,
            groundspeed_mps=22.0,
            battery_pct=87.0,
        )
    )
    assert line == (
        "12:00:01.234Z telemetry  F26E-001 65.82520,21.68860 alt 250.0 m MSL hdg 90° "
        "gs 22.0 m/s batt 87% link -"
    )


def test_telemetry_without_position_says_no_fix_and_dashes() -> None:
    (line,) = render(Telemetry(event_id="1", airframe="A", time=T0))
    assert "A no fix hdg - gs - batt -" in line
    assert " 0" not in line


def test_link_state_line() -> None:
    (line,) = render(
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
    assert line.endswith("A sdr DOWN loss 2.5% (sdr not heard for 3.0 s)")


def test_json_format_is_the_event() -> None:
    event = Telemetry(event_id="1", airframe="A", time=T0)
    (line,) = render(event, fmt="json")
    assert json.loads(line)["airframe"] == "A"
