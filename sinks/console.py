"""The console sink: one human-readable line per event, for the demo and for operators."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Literal, TextIO

from gateway.events import Detection, Event, EventKind, LinkState, Telemetry, Track
from gateway.sink import SinkConfig

__all__ = ["ConsoleSink", "ConsoleSinkConfig", "describe"]


class ConsoleSinkConfig(SinkConfig):
    """Options of the console sink."""

    kinds: frozenset[EventKind] = frozenset(EventKind)
    format: Literal["text", "json"] = "text"


def _num(value: float | None, fmt: str, unit: str = "") -> str:
    return "-" if value is None else f"{value:{fmt}}{unit}"


def describe(event: Event) -> str:
    """One line for ``event``; unknown values show as '-', never as 0."""
    stamp = event.time.strftime("%H:%M:%S.%f")[:-3] + "Z"
    head = f"{stamp} {event.kind.value:<10}"
    if isinstance(event, Telemetry):
        pos = event.position
        where = (
            "no fix"
            if pos is None
            else f"{pos.lat_deg:.5f},{pos.lon_deg:.5f} alt {_num(pos.alt_msl_m, '.1f', ' m')} MSL"
        )
        return (
            f"{head} {event.airframe} {where} hdg {_num(event.heading_deg, '.0f', '°')}"
            f" gs {_num(event.groundspeed_mps, '.1f', ' m/s')}"
            f" batt {_num(event.battery_pct, '.0f', '%')} link {event.active_link or '-'}"
        )
    if isinstance(event, LinkState):
        state = "up" if event.is_up else "DOWN"
        active = " active" if event.is_active else ""
        return (
            f"{head} {event.airframe} {event.link} {state}{active}"
            f" loss {event.loss_pct:.1f}% ({event.reason})"
        )
    if isinstance(event, Detection | Track):
        who = event.airframe if isinstance(event, Detection) else event.track_id
        pos = event.position
        return (
            f"{head} {who} {event.object_class} {event.subtype or ''} conf {event.confidence:.2f}"
            f" at {pos.lat_deg:.5f},{pos.lon_deg:.5f}"
        )
    pos = event.position
    return f"{head} {event.uid} {event.callsign} at {pos.lat_deg:.5f},{pos.lon_deg:.5f}"


class ConsoleSink:
    """Writes each event as a line to stdout (or the stream it is given)."""

    config_model = ConsoleSinkConfig

    def __init__(self, name: str, config: ConsoleSinkConfig, stream: TextIO | None = None) -> None:
        self.name = name
        self.config = config
        self._stream = stream

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Every kind unless the config narrows it."""
        return self.config.kinds

    async def open(self) -> None:
        """Nothing to open."""

    async def send(self, batch: Sequence[Event]) -> None:
        """Print one line per event."""
        stream = self._stream or sys.stdout
        if self.config.format == "json":
            lines = [event.model_dump_json() for event in batch]
        else:
            lines = [describe(event) for event in batch]
        stream.write("\n".join(lines) + "\n")
        stream.flush()

    async def aclose(self) -> None:
        """Nothing to close."""
