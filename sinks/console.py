"""The console sink: one line per event on stdout, for the demo and for operators.

``output`` chooses where: ``stdout`` (the default), ``stderr``, or a file path (appended to,
opened by ``open`` and closed by ``aclose``). The gateway's own logs go to stderr, so on a
terminal or a pipe the events on stdout stay apart from them; under systemd both streams end
up in the journal, so give a service a file path (or use the ``jsonl`` sink).

``format: text`` gives a line a person can scan (``describe``); ``format: json`` gives
``event.model_dump_json()``, which ``gateway.events.event_adapter`` reads back. An unknown value
is shown as ``-``, never as 0, and telemetry without a position says ``no fix``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from datetime import UTC
from pathlib import Path
from typing import Literal, TextIO, assert_never

import anyio
import structlog
from pydantic import Field

from gateway.c2.sink import SinkConfig
from gateway.domain.peertext import safe_text, shown
from gateway.errors import TransientSinkError
from gateway.events import (
    BlueForce,
    Detection,
    Event,
    EventKind,
    Extension,
    FiveLineOrder,
    Handoff,
    HopEvent,
    LinkState,
    OrderStatus,
    Position,
    Telemetry,
    Track,
    VideoFrameMetadata,
)
from sinks._story import Story, nearest_blue

__all__ = ["ConsoleSink", "ConsoleSinkConfig", "describe"]

log = structlog.get_logger(__name__)

#: The kind column is padded to the longest kind so the columns after it line up; the rare
#: long kinds (``video_frame_metadata``, ``order_status``) run over rather than widen every line.
_KIND_WIDTH = max(
    len(kind.value)
    for kind in EventKind
    if kind not in (EventKind.VIDEO_FRAME_METADATA, EventKind.ORDER_STATUS)
)


class ConsoleSinkConfig(SinkConfig):
    """Options of the console sink."""

    kinds: frozenset[EventKind] = Field(
        default=frozenset(EventKind), min_length=1, description="Event kinds this sink takes."
    )
    format: Literal["text", "json", "story"] = Field(
        default="text",
        description="text: a line per event; json: one JSON object per line; story: what "
        "happened in the operation's words (new friendly units, first detections, fused "
        "tracks, counter-UAS cues), not a line per event.",
    )
    output: Literal["stdout", "stderr"] | Path = Field(
        default="stdout", description="stdout, stderr, or a file path appended to."
    )
    """Where the lines go: ``stdout``, ``stderr`` or a file appended to."""


def _num(value: float | None, fmt: str, unit: str = "") -> str:
    return "-" if value is None else f"{value:{fmt}}{unit}"


def _where(position: Position) -> str:
    alt = _num(position.alt_msl_m, ".1f", " m")
    return f"{position.lat_deg:.5f},{position.lon_deg:.5f} alt {alt} MSL"


def describe(event: Event) -> str:
    """One line for ``event``: UTC time, kind, then the fields an operator looks at first.

    Unknown values show as ``-``, never as 0; telemetry without a position says ``no fix``.
    """
    stamp = event.time.astimezone(UTC).strftime("%H:%M:%S.%f")[:-3] + "Z"
    head = f"{stamp} {event.kind.value:<{_KIND_WIDTH}}"
    if isinstance(event, Telemetry):
        where = "no fix" if event.position is None else _where(event.position)
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
            f" loss {event.loss_pct:.1f}% ({event.reason or '-'})"
        )
    if isinstance(event, Detection):
        return (
            f"{head} {event.airframe} {event.sensor.value} {event.object_class}"
            f" {event.subtype or '-'} conf {event.confidence:.2f}"
            f" at {_where(event.position)} ±{event.sigma_h_m:.0f} m"
        )
    if isinstance(event, Track):
        return (
            f"{head} {event.track_id} {event.status} {event.object_class}"
            f" {event.subtype or '-'} {event.hostility} conf {event.confidence:.2f}"
            f" at {_where(event.position)} cep50 {event.cep50_m:.0f} m"
        )
    if isinstance(event, BlueForce):
        who = (
            shown(event.callsign, event.provenance, event.source, event.source_name)
            if event.callsign
            else "-"
        )
        return (
            f'{head} uid "{safe_text(event.uid, 64)}" {who} at {_where(event.position)}'
            f" via {event.source}"
        )
    if isinstance(event, Handoff):
        if event.status != "active":
            return (
                f"{head} {event.handoff_id} r{event.revision} {event.status.upper()}"
                f" (track {event.track.track_id}) at {event.battery}"
                + (f" by {event.superseded_by}" if event.superseded_by else "")
                + (f": {event.note}" if event.note else "")
            )
        blue = event.deconfliction
        nearest = (
            "no blue force known"
            if blue.nearest_blue_m is None
            else (f"nearest blue {nearest_blue(blue)} {blue.nearest_blue_m:.0f} m")
        )
        verdict = "deconfliction clear" if blue.clear else "deconfliction NOT clear"
        return (
            f"{head} {event.track.track_id} to {event.battery}"
            f" {event.range_m:.0f} m brg {event.bearing_deg:.0f}°, {verdict} ({nearest}),"
            f" recommend {event.recommended_effector or 'none'}; operator authorises"
        )
    if isinstance(event, FiveLineOrder):
        area = event.location
        place = area.mgrs or (
            _where(area.point) if area.point else f"area of {len(area.polygon)} corners"
        )
        return (
            f"{head} {event.source} {event.order_id} {event.priority.value} {event.task.value}"
            f" {place} for {event.airframe or 'any airframe'}"
        )
    if isinstance(event, HopEvent):
        return (
            f"{head} {event.airframe} {event.reason.value} to slot {event.slot}"
            f" {event.frequency_hz / 1e6:.3f} MHz schedule {event.schedule_id:08x}"
            f" hops {event.hop_count} rssi {_num(event.rssi_dbm, '.0f', ' dBm')}"
            f" interference {_num(event.interference_dbm, '.0f', ' dBm')}"
        )
    if isinstance(event, VideoFrameMetadata):
        centre = event.frame_centre
        looks = (
            f"frame centre {_where(centre)} ({event.frame_centre_source})"
            if centre is not None
            else ("off earth" if event.is_off_earth else "frame centre unknown")
        )
        return f"{head} {event.airframe} camera at {_where(event.sensor_position)}, {looks}"
    if isinstance(event, OrderStatus):
        why = f" ({event.reason})" if event.reason else ""
        return (
            f"{head} {event.source} {event.order_id} {event.status.value}"
            f" on {event.airframe or 'no airframe'}{why}"
        )
    if isinstance(event, Extension):
        return f"{head} {event.type} from {event.publisher or '-'} {event.event_id}"
    assert_never(event)


class ConsoleSink:
    """Writes each event as a line to ``stream``, or else to the configured ``output``.

    The write runs in a worker thread, so a stalled terminal or an unread pipe holds up this
    sink only, never the event loop. Such a write is abandoned when the send is cancelled
    (its deadline, shutdown); while it is still stuck, further sends fail fast with
    ``TransientSinkError`` instead of stacking up threads.
    """

    config_model = ConsoleSinkConfig

    def __init__(self, name: str, config: ConsoleSinkConfig, stream: TextIO | None = None) -> None:
        self.name = name
        self.config = config
        self._stream = stream
        self._file: TextIO | None = None
        self._writes_in_flight = 0
        self._story = Story()
        # Its own limiter: a stuck write must not hold a token of the shared thread pool.
        self._limiter = anyio.CapacityLimiter(1)

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Every kind unless the config narrows it."""
        return self.config.kinds

    async def open(self) -> None:
        """Open the output file, if ``output`` is a path; ``TransientSinkError`` if it fails."""
        output = self.config.output
        if self._stream is not None or not isinstance(output, Path) or self._file is not None:
            return
        try:
            self._file = await anyio.to_thread.run_sync(_append, output)
        except OSError as exc:
            raise TransientSinkError(
                f"sink {self.name}: cannot open {output}: {exc.strerror or exc}", sink=self.name
            ) from exc

    async def send(self, batch: Sequence[Event]) -> None:
        """Write one line per event, then flush.

        Raises ``TransientSinkError`` if the stream is still stuck in an earlier write or
        raises ``OSError`` (a closed pipe, for instance).
        """
        if not batch:
            return
        if self._writes_in_flight:
            raise TransientSinkError(
                f"sink {self.name}: the console is still blocked on an earlier write",
                sink=self.name,
            )
        if self.config.format == "json":
            text = "".join(event.model_dump_json() + "\n" for event in batch)
        elif self.config.format == "story":
            text = "".join(
                f"{event.time.astimezone(UTC):%H:%M:%S}Z {line}\n"
                for event in batch
                for line in self._story.tell(event)
            )
            if not text:
                return
        else:
            text = "".join(describe(event) + "\n" for event in batch)
        try:
            await anyio.to_thread.run_sync(
                self._write, text, abandon_on_cancel=True, limiter=self._limiter
            )
        except OSError as exc:
            log.warning("console_write_failed", sink=self.name, error=type(exc).__name__)
            raise TransientSinkError(
                f"sink {self.name}: cannot write to the console: {exc.strerror or exc}",
                sink=self.name,
            ) from exc

    async def aclose(self) -> None:
        """Close the output file, if this sink opened one; the standard streams stay open."""
        if self._file is not None:
            handle, self._file = self._file, None
            await anyio.to_thread.run_sync(handle.close)

    def _write(self, text: str) -> None:
        # Counted from inside the thread: a write cancelled before it started never runs.
        self._writes_in_flight += 1
        try:
            stream = self._stream or self._file or _standard(self.config.output)
            stream.write(text)
            stream.flush()
        finally:
            self._writes_in_flight -= 1


def _append(path: Path) -> TextIO:
    return path.open("a", encoding="utf-8")


def _standard(output: str | Path) -> TextIO:
    # Looked up at each write, not kept: tests and the demo replace sys.stdout.
    return sys.stderr if output == "stderr" else sys.stdout
