"""Reading the scorer's inputs: a truth file (``simulate --truth``) and a JSONL archive.

Both are untrusted. A truth file must be exactly what ``gateway.sim.truth`` writes: any
line that is not is a ``ScoreInputError`` naming the file and line. An archive is read for
its Track and Handoff events only; other kinds are passed over without being validated, and
a line that is not a readable event (a file cut mid-line by a crash, a foreign line) is
counted in ``Tracks.skipped_lines``, not fatal. Lines longer than ``MAX_LINE_BYTES`` are
refused, so a file without newlines cannot take the memory.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from gateway.errors import ScoreInputError
from gateway.events import Handoff, Track
from gateway.scoring.model import Plane, TrackReport, Tracks, TruthFrame, TruthRun, TruthTarget
from gateway.sim.truth import TRUTH_FORMAT

__all__ = [
    "MAX_LINE_BYTES",
    "archive_tracks",
    "parse_truth",
    "read_archive",
    "read_truth",
    "tracks_from_events",
]

#: The longest line either file may hold.
MAX_LINE_BYTES = 1 << 20


def _lines(path: Path) -> Iterator[tuple[int, bytes]]:
    try:
        with path.open("rb") as f:
            number = 0
            while True:
                line = f.readline(MAX_LINE_BYTES + 1)
                if not line:
                    return
                number += 1
                if len(line) > MAX_LINE_BYTES:
                    raise ScoreInputError(str(path), number, f"line over {MAX_LINE_BYTES} bytes")
                yield number, line
    except OSError as exc:
        raise ScoreInputError(str(path), None, exc.strerror or str(exc)) from exc


def _unix(text: object, source: str, line: int) -> float:
    if not isinstance(text, str):
        raise ScoreInputError(source, line, f"expected an ISO 8601 time, got {text!r}")
    try:
        moment = datetime.fromisoformat(text)
    except ValueError as exc:
        raise ScoreInputError(source, line, f"expected an ISO 8601 time, got {text!r}") from exc
    if moment.tzinfo is None:
        raise ScoreInputError(source, line, f"expected a time with its zone, got {text!r}")
    return moment.timestamp()


def _number(record: dict[str, Any], key: str, source: str, line: int) -> float:
    value = record.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ScoreInputError(source, line, f"{key}: expected a finite number, got {value!r}")
    return float(value)


def _text(record: dict[str, Any], key: str, source: str, line: int) -> str:
    value = record.get(key)
    if not isinstance(value, str):
        raise ScoreInputError(source, line, f"{key}: expected a string, got {value!r}")
    return value


def _json_object(raw: bytes, source: str, line: int) -> dict[str, Any]:
    try:
        record = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ScoreInputError(source, line, "not a JSON line") from exc
    if not isinstance(record, dict):
        raise ScoreInputError(source, line, "expected a JSON object")
    return record


def read_truth(path: Path) -> TruthRun:
    """The truth file at ``path`` as frames, one per step from 0 to its duration."""
    return parse_truth(_lines(path), str(path))


def parse_truth(lines: Iterator[tuple[int, bytes]], source: str) -> TruthRun:
    """Truth from numbered lines (``source`` names them in errors); see ``read_truth``."""
    first = next(lines, None)
    if first is None:
        raise ScoreInputError(source, None, "empty: expected a truth header line")
    header = _json_object(first[1], source, 1)
    if header.get("format") != TRUTH_FORMAT:
        raise ScoreInputError(source, 1, f"expected a header with format {TRUTH_FORMAT!r}")
    start = _unix(header.get("start_utc"), source, 1)
    speed = _number(header, "speed", source, 1)
    step = _number(header, "step_s", source, 1)
    duration = _number(header, "duration_s", source, 1)
    targets = header.get("targets")
    if not (speed > 0 and step > 0 and 0 < duration <= 86_400 and duration / step <= 1e6):
        raise ScoreInputError(source, 1, "speed, step_s and duration_s out of range")
    if not isinstance(targets, list) or not all(isinstance(t, str) for t in targets):
        raise ScoreInputError(source, 1, "targets: expected a list of target ids")
    steps = math.floor(duration / step + 1e-9) + 1
    by_step: list[list[TruthTarget]] = [[] for _ in range(steps)]
    plane: Plane | None = None
    for number, raw in lines:
        record = _json_object(raw, source, number)
        t_s = _number(record, "t_s", source, number)
        k = round(t_s / step)
        if not 0 <= k < steps or abs(k * step - t_s) > 1e-6:
            raise ScoreInputError(source, number, f"t_s {t_s!r} is not a step of the run")
        lat = _number(record, "lat_deg", source, number)
        lon = _number(record, "lon_deg", source, number)
        if not (-90 <= lat <= 90 and -180 <= lon <= 180):
            raise ScoreInputError(source, number, "lat_deg/lon_deg out of range")
        if plane is None:
            plane = Plane(lat, lon)
        x, y = plane.xy(lat, lon)
        by_step[k].append(
            TruthTarget(
                target=_text(record, "target", source, number),
                object_class=_text(record, "object_class", source, number),
                affiliation=_text(record, "affiliation", source, number),
                x=x,
                y=y,
                vn=_number(record, "north_mps", source, number),
                ve=_number(record, "east_mps", source, number),
            )
        )
    frames = tuple(
        TruthFrame(t_s=k * step, unix_s=start + k * step / speed, targets=tuple(found))
        for k, found in enumerate(by_step)
    )
    return TruthRun(
        scenario=str(header.get("scenario", "")),
        speed=speed,
        step_s=step,
        frames=frames,
        plane=plane or Plane(0.0, 0.0),
        target_ids=tuple(targets),
    )


def _report(track: Track, plane: Plane) -> TrackReport:
    x, y = plane.xy(track.position.lat_deg, track.position.lon_deg)
    v = track.velocity
    return TrackReport(
        unix_s=track.time.timestamp(),
        x=x,
        y=y,
        vn=v.north_mps if v is not None else None,
        ve=v.east_mps if v is not None else None,
        status=track.status,
        object_class=track.object_class,
    )


def _take(tracks: Tracks, event: Track | Handoff, plane: Plane) -> None:
    if isinstance(event, Track):
        tracks.add(event.track_id, _report(event, plane))
    elif event.handoff_id not in tracks.cues:
        report = _report(event.track, plane)
        tracks.cues[event.handoff_id] = (report.unix_s, report.x, report.y)


def tracks_from_events(events: Iterable[Track | Handoff], plane: Plane) -> Tracks:
    """Track events as histories and Handoff events as cues, in ``plane``."""
    tracks = Tracks()
    for event in events:
        _take(tracks, event, plane)
    tracks.sort()
    return tracks


def _archive_events(path: Path, tracks: Tracks) -> Iterator[Track | Handoff]:
    for number, raw in _lines(path):
        if b'"kind":"track"' not in raw and b'"kind":"handoff"' not in raw:
            continue  # other kinds are not scored; no need to validate them
        try:
            record = json.loads(raw)
            kind = record.get("kind") if isinstance(record, dict) else None
            if kind == "track":
                yield Track.model_validate(record)
            elif kind == "handoff":
                yield Handoff.model_validate(record)
        except (ValueError, UnicodeDecodeError, ValidationError):
            tracks.skipped_lines += 1
            if tracks.first_skipped_line is None:
                tracks.first_skipped_line = number


def read_archive(paths: Iterable[Path], plane: Plane) -> Tracks:
    """Every Track and Handoff event of the archive files (in order), in ``plane``; each
    event is reduced to what the scorer needs as it is read."""
    tracks = Tracks()
    for path in paths:
        for event in _archive_events(path, tracks):
            _take(tracks, event, plane)
    tracks.sort()
    return tracks


def archive_tracks(paths: Iterable[Path]) -> list[Track]:
    """Every Track event of the archive files, in order (unreadable lines passed over)."""
    skipped = Tracks()
    return [
        event
        for path in paths
        for event in _archive_events(path, skipped)
        if isinstance(event, Track)
    ]
