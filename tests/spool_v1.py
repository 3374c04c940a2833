"""A spool file of schema 1, as the gateway wrote it before schema 2 (one owed row per sink).

The tables are schema 1's, verbatim, and the rows are what its ``Spool`` wrote: an event's
JSON once in ``events``, a ``pending`` row per (sink, seq) still owed, an ``events`` row gone
with its last ``pending`` row, dead letters and the detection ids taken in. Checked against a
file the schema 1 code itself wrote (same tables, same rows for the same calls).
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from gateway.events import Event

V1_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS events (
    seq INTEGER PRIMARY KEY,
    event_id TEXT NOT NULL,
    kind TEXT NOT NULL,
    body BLOB NOT NULL,
    spooled_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS pending (
    sink TEXT NOT NULL,
    seq INTEGER NOT NULL,
    PRIMARY KEY (sink, seq)
) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS pending_seq ON pending (seq);
CREATE TABLE IF NOT EXISTS dead_letters (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    sink TEXT NOT NULL,
    event_id TEXT NOT NULL,
    kind TEXT NOT NULL,
    body BLOB NOT NULL,
    reason TEXT NOT NULL,
    spooled_at REAL NOT NULL,
    dead_at REAL NOT NULL,
    requeue INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS dead_letters_sink ON dead_letters (sink);
CREATE INDEX IF NOT EXISTS dead_letters_requeue ON dead_letters (requeue) WHERE requeue = 1;
CREATE TABLE IF NOT EXISTS seen (event_id TEXT PRIMARY KEY, at REAL NOT NULL) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS seen_at ON seen (at);
"""


def write_v1(
    path: Path,
    events: Sequence[Event],
    owed: Mapping[str, Sequence[int]],
    *,
    dead: Sequence[tuple[str, Event, str]] = (),
    seen: Sequence[str] = (),
) -> None:
    """A schema 1 spool at ``path``: ``events`` numbered from 1, ``owed`` sink -> indexes.

    An event owed to no sink is not written (schema 1 deleted it with its last owed row).
    """
    db = sqlite3.connect(path, isolation_level=None)
    try:
        db.execute("PRAGMA journal_mode=WAL")
        db.executescript(V1_SCHEMA)
        db.execute("BEGIN IMMEDIATE")
        db.execute("INSERT INTO meta VALUES ('schema', '1')")
        now = time.time()
        wanted = {index for indexes in owed.values() for index in indexes}
        for index, event in enumerate(events):
            if index in wanted:
                db.execute(
                    "INSERT INTO events VALUES (?, ?, ?, ?, ?)",
                    (
                        index + 1,
                        event.event_id,
                        event.kind.value,
                        event.model_dump_json().encode(),
                        now,
                    ),
                )
        for sink, indexes in owed.items():
            db.executemany("INSERT INTO pending VALUES (?, ?)", [(sink, i + 1) for i in indexes])
        for sink, event, reason in dead:
            db.execute(
                "INSERT INTO dead_letters (sink, event_id, kind, body, reason, spooled_at, dead_at)"
                " VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    sink,
                    event.event_id,
                    event.kind.value,
                    event.model_dump_json().encode(),
                    reason,
                    now,
                    now,
                ),
            )
        db.executemany("INSERT INTO seen VALUES (?, ?)", [(i, now) for i in seen])
        db.execute("COMMIT")
    finally:
        db.close()
