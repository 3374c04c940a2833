"""The ``fischer-gateway spool`` command: look into a spool and re-queue dead letters.

It opens the spool file beside a running gateway (``exclusive=False``); SQLite's locking keeps
the two consistent, and the gateway picks re-queued events up when it next polls its spool
(within ``IDLE_POLL_S`` of a sink going idle).
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import TextIO

from gateway.spool.store import Spool

__all__ = ["dead_letters", "requeue", "show", "status"]


def _when(unix_s: float) -> str:
    return datetime.fromtimestamp(unix_s, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def status(spool: Spool, out: TextIO) -> int:
    """Size, what each sink is owed, and the dead letters by sink."""
    pct = 100.0 * spool.size_bytes / spool.max_bytes
    print(
        f"spool {spool.path}: {spool.size_bytes:,} of {spool.max_bytes:,} bytes ({pct:.1f} %)",
        file=out,
    )
    owed = spool.pending_counts()
    if not owed:
        print("  nothing owed to any sink", file=out)
    for sink, count in sorted(owed.items()):
        print(f"  sink {sink}: {count:,} events owed", file=out)
    letters = spool.dead_letters(limit=spool.dead_letters_max)
    by_sink = Counter(letter.sink for letter in letters)
    print(f"  dead letters: {len(letters):,}", file=out)
    for sink, count in sorted(by_sink.items()):
        print(f"    sink {sink}: {count:,}", file=out)
    return 0


def dead_letters(spool: Spool, out: TextIO, *, sink: str | None, limit: int, as_json: bool) -> int:
    """List dead letters, newest first: id, sink, kind, event id, when, reason."""
    letters = spool.dead_letters(sink, limit=limit)
    for letter in letters:
        if as_json:
            record = {
                "id": letter.id,
                "sink": letter.sink,
                "kind": letter.kind,
                "event_id": letter.event_id,
                "spooled_at": _when(letter.spooled_at),
                "dead_at": _when(letter.dead_at),
                "reason": letter.reason,
            }
            print(json.dumps(record), file=out)
        else:
            print(
                f"{letter.id:>8} {letter.sink} {letter.kind} {letter.event_id} "
                f"{_when(letter.dead_at)} {letter.reason}",
                file=out,
            )
    if not letters and not as_json:
        print("no dead letters" + (f" for sink {sink}" if sink else ""), file=out)
    return 0


def show(spool: Spool, out: TextIO, err: TextIO, letter_id: int) -> int:
    """Print one dead letter as JSON: id, sink, reason, times, and the event itself."""
    body = spool.dead_letter_body(letter_id)
    letter = spool.dead_letter_by_id(letter_id)
    if body is None or letter is None:
        print(f"no dead letter {letter_id}", file=err)
        return 1
    record = {
        "id": letter.id,
        "sink": letter.sink,
        "reason": letter.reason,
        "spooled_at": _when(letter.spooled_at),
        "dead_at": _when(letter.dead_at),
        "event": json.loads(body),
    }
    print(json.dumps(record, indent=2), file=out)
    return 0


def requeue(
    spool: Spool, out: TextIO, err: TextIO, ids: Sequence[int], *, every: bool, sink: str | None
) -> int:
    """Put dead letters back in their sink's queue; exit 1 if named ones do not exist."""
    if not every and not ids:
        print("name dead letter ids, or --all", file=err)
        return 2
    moved = spool.requeue(None if every else ids, sink=sink)
    print(f"re-queued {moved} dead letter(s)", file=out)
    if not every and moved < len(set(ids)):
        print(f"{len(set(ids)) - moved} of the ids named are not dead letters here", file=err)
        return 1
    return 0
