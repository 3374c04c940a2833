"""The picture as it was: the JSONL archive read back up to an instant (docs/map.md §6).

The map's time slider asks for the picture at a past instant ``at``. It is rebuilt from the
files of a ``jsonl`` sink (the live file and its rotated files, named as that sink names them:
``<stem>-YYYYmmddTHHMMSSZ[-N]<suffix>``, the stamp being when the file was opened) by folding
the archived events stamped at or before ``at`` into a fresh ``Picture`` with the live map's
limits, then removing what had not been updated for ``expire_after_s`` by then.

Only the files that can hold events of the window ``[at - expire_after_s, at]`` are opened
(a rotated file ends where the next one starts), and in each only the bytes of the window are
read: the archive is in arrival order, so nearly in time order, and bisection finds where the
window starts and ends, give or take ``TAIL_S``. The archive is input like any other: a line
that is too long, not JSON or not an event is skipped and counted. Each request is bounded: at
most ``max_bytes`` read (when the window holds more, its newest ``max_bytes``, those nearest
``at``, and the answer says ``truncated``) and ``max_seconds`` spent, and memory by the
picture's own caps: only the events that can still show at ``at`` are kept (the last of each
airframe, unit and order, the last ``history_points`` of each track, the last
``cue_revisions`` of each cue, the last ``max_detections`` detections), each kind's keys
capped like the picture's layers. No path comes from the client.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

from pydantic import ValidationError

from gateway.events import event_adapter
from sinks.map.picture import Limits, Picture

__all__ = [
    "LATE_S",
    "TAIL_S",
    "ArchiveBudget",
    "Replay",
    "archive_files",
    "archive_start",
    "replay",
]

#: A rotated file is read when it may hold the window give or take this long (clocks differ).
LATE_S = 120.0
#: Within a file, the lines read are those of the window give or take this long: an event
#: written more than this long after its time, in the last seconds before ``at``, is missed.
TAIL_S = 10.0
_STAMP = "%Y%m%dT%H%M%SZ"
_MAX_LINE = 1024 * 1024
#: Bisection into a file stops when the range is this small (then lines are read).
_SEEK_GRAIN = 64 * 1024
#: A byte range of one archive file: path, start, end, and whether start may be mid-line.
_Span = tuple[Path, int, int, bool]


@dataclass(frozen=True, slots=True)
class ArchiveBudget:
    """What one replay may cost."""

    max_bytes: int = 64 * 1024 * 1024
    max_seconds: float = 10.0
    max_line_bytes: int = _MAX_LINE


@dataclass(slots=True)
class Replay:
    """A replay's picture and what reading the archive took."""

    at: datetime
    picture: Picture
    files: int = 0
    bytes_read: int = 0
    lines: int = 0
    events: int = 0
    skipped: int = 0
    truncated: str | None = None
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """The JSON-ready account of the replay (the answer's ``replay`` member)."""
        return {
            "files": self.files,
            "bytes_read": self.bytes_read,
            "lines": self.lines,
            "events": self.events,
            "skipped": self.skipped,
            "truncated": self.truncated,
        }


def archive_files(live: Path) -> list[tuple[datetime | None, Path]]:
    """The archive's files, oldest first, each with when it was opened (None: the live file)."""
    stem, suffix = re.escape(live.stem), re.escape(live.suffix)
    pattern = re.compile(rf"{stem}-(\d{{8}}T\d{{6}}Z)(?:-(\d+))?{suffix}")
    rotated: list[tuple[str, int, Path]] = []
    try:
        entries = list(live.parent.iterdir())
    except OSError:
        entries = []
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        if match and entry.is_file():
            rotated.append((match[1], int(match[2] or 0), entry))
    rotated.sort()
    files: list[tuple[datetime | None, Path]] = [
        (datetime.strptime(stamp, _STAMP).replace(tzinfo=UTC), path) for stamp, _, path in rotated
    ]
    if live.is_file():
        files.append((None, live))
    return files


def _lines(
    path: Path,
    budget: ArchiveBudget,
    state: Replay,
    start: int = 0,
    end: int | None = None,
    *,
    mid_line: bool = False,
) -> Iterator[bytes]:
    """The lines of ``path`` starting in ``[start, end)`` (``mid_line``: from the first whole
    line); one longer than the budget allows is skipped whole."""
    with path.open("rb") as handle:
        handle.seek(start)
        if mid_line and start > 0:
            state.bytes_read += _skip_line(handle, budget.max_line_bytes)
        while end is None or handle.tell() < end:
            line = handle.readline(budget.max_line_bytes + 1)
            if not line:
                return
            state.bytes_read += len(line)
            if len(line) > budget.max_line_bytes:
                state.skipped += 1
                if not line.endswith(b"\n"):
                    state.bytes_read += _skip_line(handle, budget.max_line_bytes)
                continue
            yield line


def _skip_line(handle: BinaryIO, max_line: int) -> int:
    """Read to the end of the current line; how many bytes that was."""
    total = 0
    while True:
        chunk = handle.readline(max_line + 1)
        total += len(chunk)
        if not chunk or chunk.endswith(b"\n"):
            return total


def _stamp_of(line: bytes) -> datetime | None:
    try:
        obj = json.loads(line)
    except ValueError:
        return None
    return _time(obj.get("time")) if isinstance(obj, dict) else None


def _offset_before(handle: BinaryIO, size: int, threshold: float, max_line: int) -> int:
    """Where the first line stamped after ``threshold`` starts (or the end): bisection down to
    ``_SEEK_GRAIN`` bytes, then line by line (the archive is in arrival order, so nearly in
    time order)."""
    low, high = 0, size
    while high - low > _SEEK_GRAIN:
        middle = (low + high) // 2
        handle.seek(middle)
        _skip_line(handle, max_line)
        start = handle.tell()
        stamp = None
        for _ in range(8):  # the first line with a time, among the next few
            line = handle.readline(max_line + 1)
            if not line:
                break
            stamp = _stamp_of(line)
            if stamp is not None:
                break
        if stamp is None or stamp.timestamp() > threshold or start >= high:
            high = middle
        else:
            low = start
    handle.seek(low)  # then line by line, to the first line stamped after ``threshold``
    position = low
    while position < high:
        line = handle.readline(max_line + 1)
        if not line:
            break
        stamp = _stamp_of(line)
        if stamp is not None and stamp.timestamp() > threshold:
            break
        position += len(line)
    return position


def _time(raw: Any) -> datetime | None:
    if not isinstance(raw, str) or len(raw) > 64:
        return None
    try:
        stamp = datetime.fromisoformat(raw)
    except ValueError:
        return None
    return stamp if stamp.tzinfo is not None else None


class _Kept:
    """The archived events that can still show at ``at``, bounded like the picture."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self.buckets: dict[str, OrderedDict[str, deque[tuple[int, dict[str, Any]]]]] = {}
        self.n = 0

    def _slot(self, obj: dict[str, Any]) -> tuple[str, str, int, int] | None:
        """(bucket, key, events kept per key, keys kept) for a map kind; None for others."""
        lim = self.limits
        match obj.get("kind"):
            case "telemetry":
                return "telemetry", str(obj.get("airframe")), 1, lim.airframes
            case "link_state":
                key = f"{obj.get('airframe')}\x00{obj.get('link')}"
                return "link_state", key, 1, lim.airframes * 8
            case "track":
                return "track", str(obj.get("track_id")), lim.history_points, lim.tracks
            case "blue_force":
                return "blue_force", str(obj.get("uid")), 1, lim.blue
            case "handoff":
                return "handoff", str(obj.get("handoff_id")), lim.cue_revisions, lim.cues
            case "order":
                return "order", str(obj.get("event_id")), 1, lim.orders
            case "order_status":
                return "order_status", str(obj.get("order_event_id")), 1, lim.orders
            case "detection":
                return "detection", "", lim.detections, 1
        return None

    def add(self, obj: dict[str, Any]) -> bool:
        """Keep ``obj`` if it is of a kind the map draws; False if it is not."""
        slot = self._slot(obj)
        if slot is None:
            return False
        name, key, depth, keys = slot
        if depth == 0:
            return True  # the layer is switched off (max_detections: 0)
        bucket = self.buckets.setdefault(name, OrderedDict())
        held = bucket.get(key)
        if held is None:
            while len(bucket) >= keys:
                bucket.popitem(last=False)
            held = bucket[key] = deque(maxlen=depth)
        else:
            bucket.move_to_end(key)
        self.n += 1
        held.append((self.n, obj))
        return True

    def in_order(self) -> list[dict[str, Any]]:
        """Every kept event, in archive order."""
        kept = [
            item for bucket in self.buckets.values() for held in bucket.values() for item in held
        ]
        kept.sort(key=lambda item: item[0])
        return [obj for _, obj in kept]


def replay(
    live: Path,
    at: datetime,
    limits: Limits,
    budget: ArchiveBudget,
    *,
    clock: Callable[[], float] = time.monotonic,
) -> Replay:
    """The picture at ``at`` from the archive whose live file is ``live``; blocking I/O."""
    started = clock()
    window = at.timestamp() - limits.expire_after_s
    files = archive_files(live)
    moment = [0.0]
    picture = Picture(limits, clock=lambda: moment[0])
    state = Replay(at=at, picture=picture)
    kept = _Kept(limits)
    spans = _window_spans(files, at.timestamp(), window, budget)
    if sum(end - begin for _, begin, end, _ in spans) > budget.max_bytes:
        spans = _newest(spans, budget.max_bytes)
        state.truncated = f"the window holds more than {budget.max_bytes} bytes: read its newest"
    limit = budget.max_bytes + 2 * _SEEK_GRAIN + budget.max_line_bytes
    for path, begin, end, mid_line in spans:
        state.files += 1
        try:
            for line in _lines(path, budget, state, begin, end, mid_line=mid_line):
                state.lines += 1
                if state.bytes_read > limit:
                    state.truncated = f"read {budget.max_bytes} bytes"
                    break
                if state.lines % 4096 == 0 and clock() - started > budget.max_seconds:
                    state.truncated = f"took {budget.max_seconds:g} s"
                    break
                try:
                    obj = json.loads(line)
                except ValueError:
                    state.skipped += 1
                    continue
                stamp = _time(obj.get("time")) if isinstance(obj, dict) else None
                if stamp is None:
                    state.skipped += 1
                    continue
                if stamp > at:
                    if stamp.timestamp() > at.timestamp() + LATE_S:
                        break  # arrival order: the rest of this file came later still
                    continue
                if stamp.timestamp() >= window:
                    kept.add(obj)
        except OSError as exc:  # rotated away or pruned while being read
            state.notes.append(f"{path.name}: {exc.strerror or type(exc).__name__}")
        if state.truncated is not None and not state.truncated.startswith("the window"):
            break
    for obj in kept.in_order():
        try:
            event = event_adapter.validate_python(obj)
        except ValidationError:
            state.skipped += 1
            continue
        moment[0] = event.time.timestamp()
        picture.apply(event)
        state.events += 1
    moment[0] = at.timestamp()
    picture.expire()
    return state


def _window_spans(
    files: list[tuple[datetime | None, Path]], at: float, window: float, budget: ArchiveBudget
) -> list[_Span]:
    """The byte ranges of the files that can hold the window ``[window, at]``, oldest first."""
    spans: list[_Span] = []
    for index, (opened, path) in enumerate(files):
        following = files[index + 1][0] if index + 1 < len(files) else None
        if opened is not None and opened.timestamp() > at + LATE_S:
            break  # this file and the rest were opened after ``at``
        if following is not None and following.timestamp() < window - LATE_S:
            continue  # closed before the window opened
        try:
            with path.open("rb") as handle:
                size = os.fstat(handle.fileno()).st_size
                limit = budget.max_line_bytes
                begin = _offset_before(handle, size, window - TAIL_S, limit)
                end = _offset_before(handle, size, at + TAIL_S, limit)
        except OSError:
            continue  # pruned meanwhile
        spans.append((path, begin, max(begin, end), False))
    return spans


def _newest(spans: list[_Span], budget: int) -> list[_Span]:
    """The newest ``budget`` bytes of ``spans``: the part of the window nearest ``at``."""
    kept: list[_Span] = []
    for path, begin, end, _ in reversed(spans):
        if budget <= 0:
            break
        start = max(begin, end - budget)
        kept.append((path, start, end, start > begin))  # cut mid-line: start at the next
        budget -= end - start
    return kept[::-1]


def archive_start(live: Path, budget: ArchiveBudget) -> datetime | None:
    """When the oldest archived event was stamped (its file's first event); None if none."""
    for _, path in archive_files(live):
        probe = Replay(at=datetime.now(UTC), picture=Picture(Limits()))
        try:
            for count, line in enumerate(_lines(path, budget, probe)):
                if count >= 8:
                    break
                try:
                    obj = json.loads(line)
                except ValueError:
                    continue
                stamp = _time(obj.get("time")) if isinstance(obj, dict) else None
                if stamp is not None:
                    return stamp
        except OSError:
            continue
    return None
