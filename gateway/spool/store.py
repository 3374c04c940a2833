"""The spool: durable events in SQLite until every sink they go to has confirmed them.

One database (WAL journal) holds:

- ``events``: one row per durable event (its JSON body once, however many sinks take it),
  numbered by ``seq``, which only grows while the gateway runs (only the gateway numbers
  events: a re-queue from the command line marks the dead letter, and the gateway moves it
  back), so a sink's order is ``seq`` order;
- ``sinks``: the sinks events are owed to, each with a bit (0-62) of ``events.owed``;
- ``events.owed``: the sinks still owed the event, one bit each; a sink's confirmation (or
  dead letter) clears its bit, and the row goes when no bit is left. One row per event
  however many sinks take it (schema 1 kept a ``pending`` row per sink and event, which cost
  most of an append's time with five sinks; a schema 1 file is migrated at start, in one
  transaction, ``_migrate_v1``). A sink's owed events are read in ``seq`` order from the
  primary key, skipping those owed only to others; what each sink is owed is counted once at
  start and kept in memory (only the gateway that holds the file writes ``owed``);
- ``dead_letters``: events a sink refused for good or that expired, with the reason, until an
  operator re-queues them (``requeue``) or the cap pushes the oldest out;
- ``seen``: detection ids already taken in, so an airframe's re-send is acknowledged again but
  not delivered twice; kept for ``dedup_window_s``.

Durability: writes are group-committed (``gateway.spool.group``). With the event loop running,
every write of one loop pass (the events the bus appends for all their sinks, the detection
ids the intake remembers, the sinks' confirmations and dead letters) joins one transaction,
committed at the end of the pass, or earlier by ``flush`` (a sink runner about to send an event
of the open group commits it first: nothing is sent before it is held) or by the end of a
``batch()`` scope; those who must act only once it is durable ask ``Commit.when_done`` (the
detection acknowledgements). Without a loop (the ``spool`` command) each write commits at once.
A group of confirmations alone may wait up to ``SETTLE_LINGER_S`` past its pass for the other
sinks' confirmations: a kill -9 before it commits costs a re-delivery (receivers drop it by
event id), never a loss. ``sync="normal"`` (WAL with
``synchronous=NORMAL``) survives kill -9 and any crash of the process, since a commit is in the
operating system's cache when it returns; a power cut can lose the newest commits. ``"full"``
adds an fsync per commit. All calls are synchronous and short, made on the event loop.

Checkpoints (copying the WAL's pages into the database file, with an fsync of it) are not
made by a commit on the event loop: the gateway's own connection runs with
``wal_autocheckpoint=0`` and ``gateway.spool.checkpoint`` makes PASSIVE checkpoints from a
worker thread on a connection of its own, and only past ``WAL_HARD_BYTES`` a blocking one on
the loop. A checkpoint moves committed pages only; it changes nothing of the above.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import functools
import os
import sqlite3
import time
import weakref
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import structlog

from gateway.errors import SpoolError
from gateway.events import Event, event_adapter
from gateway.ops.logsetup import RateLimit
from gateway.spool.checkpoint import WAL_SOFT_BYTES, Checkpointer
from gateway.spool.commits import Commits
from gateway.spool.group import Commit
from gateway.spool.startcheck import StartCheck, create_private, open_checked

__all__ = ["MAX_SINKS", "SETTLE_LINGER_S", "DeadLetter", "Spool", "Spooled"]

log = structlog.get_logger(__name__)

_SCHEMA_VERSION = "2"
_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS sinks (
    bit INTEGER PRIMARY KEY CHECK (bit BETWEEN 0 AND 62),
    name TEXT NOT NULL UNIQUE
);
CREATE TABLE IF NOT EXISTS events (
    seq INTEGER PRIMARY KEY,
    event_id TEXT NOT NULL,
    kind TEXT NOT NULL,
    body BLOB NOT NULL,
    spooled_at REAL NOT NULL,
    owed INTEGER NOT NULL DEFAULT 0
);
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
#: Sinks one spool can owe events to at once (bits of ``events.owed``; a sink owed nothing
#: gives its bit up to a new one).
MAX_SINKS = 63
#: How often (appends) the size is measured against the cap; between, it is estimated.
_SIZE_CHECK_EVERY = 256
_SEEN_PRUNE_EVERY = 1024
_SEEN_PRUNE_CHUNK = 10_000
_ROLLED_BACK_KEEP = 100_000
#: How long a group of confirmations and dead letters alone, that no one waits on, may wait
#: past its pass for more of them (a kill -9 meanwhile costs a re-delivery, never a loss).
SETTLE_LINGER_S = 0.02
_FULL_LOG_INTERVAL_S = 10.0
_WARN_LOG_INTERVAL_S = 60.0


def _loop_running() -> bool:
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


@dataclass(frozen=True, slots=True)
class Spooled:
    """One pending event of one sink, read back from the spool."""

    seq: int
    event: Event
    spooled_at: float


@dataclass(frozen=True, slots=True)
class DeadLetter:
    """One dead-lettered event, as ``fischer-gateway spool dead-letters`` lists it."""

    id: int
    sink: str
    event_id: str
    kind: str
    reason: str
    spooled_at: float
    dead_at: float


def _lock(path: Path) -> BinaryIO:
    """Hold ``<path>.lock`` exclusively: two gateways on one spool would deliver twice."""
    real = path.resolve()  # a symlink to the same file is the same spool
    lock_path = real.with_name(real.name + ".lock")
    try:
        handle = os.fdopen(os.open(lock_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600), "ab")
    except OSError as exc:
        raise SpoolError(f"{lock_path}: {exc.strerror or exc}") from exc
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise SpoolError(
            f"{path}: in use by another running fischer-gateway; one spool belongs to one "
            "gateway (the 'spool' command may look in beside it)"
        ) from None
    return handle


class Spool:
    """The spool of one gateway; ``path`` None keeps it in memory (gone with the process).

    The gateway holds the file exclusively (``<path>.lock``); the ``spool`` command opens it
    with ``exclusive=False`` beside a running gateway, which picks up re-queued events when
    it next polls (``Outbox.poll``).
    """

    def __init__(
        self,
        path: Path | None = None,
        *,
        sync: str = "normal",
        max_bytes: int = 1 << 30,
        warn_pct: float = 80.0,
        dedup_window_s: float = 3600.0,
        dead_letters_max: int = 100_000,
        seen_max: int = 1_000_000,
        exclusive: bool = True,
    ) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self.warn_bytes = int(max_bytes * warn_pct / 100.0)
        self.dedup_window_s = dedup_window_s
        self.dead_letters_max = dead_letters_max
        self.seen_max = seen_max
        target = ":memory:" if path is None else str(path)
        self._owner = exclusive
        self._lock = _lock(path) if path is not None and exclusive else None
        #: What the check at start found (the gateway's own spool file only).
        self.start_check = StartCheck()
        #: Writes that failed to commit.
        self.commits = Commits(target)
        try:
            if path is not None and exclusive:
                create_private(path)
                connect = functools.partial(self._connect, target, sync, exclusive=exclusive)
                self._db, self.start_check = open_checked(path, connect)
            else:
                self._db = self._connect(target, sync, exclusive=exclusive)
            self._open_schema(migrate=exclusive)
        except BaseException as exc:
            self._abandon()  # the file and its lock are free for the next attempt
            if isinstance(exc, sqlite3.Error):
                raise SpoolError(f"{target}: {exc}") from exc
            if isinstance(exc, OSError):  # a damaged spool that cannot be moved aside
                raise SpoolError(f"{target}: cannot move the damaged spool aside: {exc}") from exc
            raise
        db = self._db
        self._where = target
        self._scopes = 0  # open batch() scopes
        self._group: Commit | None = None  # the writes not committed yet
        self._settles = 0
        #: Sequence numbers appended in a batch that then failed to commit: never delivered.
        self.rolled_back: set[int] = set()
        self._appends = 0
        self._bytes = self._measure()
        self._refused = 0
        self._full_log = RateLimit(interval_s=_FULL_LOG_INTERVAL_S)
        self._warn_log = RateLimit(interval_s=_WARN_LOG_INTERVAL_S)
        self._bits: dict[str, int] = {}
        self._masks: dict[tuple[str, ...], int] = {}
        self._load_bits()
        self._pending: Counter[str] = Counter()
        for owed, count in db.execute("SELECT owed, count(*) FROM events GROUP BY owed"):
            for sink, bit in self._bits.items():
                if int(owed) >> bit & 1:
                    self._pending[sink] += int(count)
        self._dead = int(db.execute("SELECT count(*) FROM dead_letters").fetchone()[0])
        self._seq = int(db.execute("SELECT coalesce(max(seq), 0) FROM events").fetchone()[0])
        self._seen_rows = int(db.execute("SELECT count(*) FROM seen").fetchone()[0])
        #: The checkpoints of the gateway's own spool file (None for memory or the command).
        self.checkpointer: Checkpointer | None = None
        if path is not None and exclusive:
            # The worker holds the spool weakly: one dropped unclosed stops its worker.
            self.checkpointer = Checkpointer(
                path,
                weakref.WeakMethod(self._checkpoint_now),
                finish=weakref.WeakMethod(self._checkpoint_rest),
            )
            weakref.finalize(self, self.checkpointer.halt)
            self.checkpointer.start()
        if exclusive:
            while True:  # at start, all of it: ids past the window are of no use
                before = self._seen_rows
                self._prune_seen()
                if self._seen_rows == before or self._seen_rows == 0:
                    break

    # -- housekeeping ---------------------------------------------------------------------

    def _connect(self, target: str, sync: str, *, exclusive: bool) -> sqlite3.Connection:
        db = sqlite3.connect(target, isolation_level=None, check_same_thread=False, timeout=0.0)
        try:
            if self.path is not None:
                mode = db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
                if str(mode).lower() != "wal":
                    raise SpoolError(f"{self.path}: the file system does not support WAL ({mode})")
            db.execute(f"PRAGMA synchronous={'FULL' if sync == 'full' else 'NORMAL'}")
            # The gateway waits at most this for the 'spool' command's short writes (on the
            # event loop, so short); the command itself waits longer for the gateway's.
            db.execute(f"PRAGMA busy_timeout={250 if exclusive else 5000}")
            db.execute("PRAGMA foreign_keys=OFF")
            if self.path is not None and exclusive:
                # No checkpoint inside a commit on the event loop: ``gateway.spool.checkpoint``.
                db.execute("PRAGMA wal_autocheckpoint=0")
                db.execute(f"PRAGMA journal_size_limit={WAL_SOFT_BYTES}")
        except BaseException:
            db.close()
            raise
        return db

    def _abandon(self) -> None:
        """Close what a failed ``__init__`` opened."""
        db = getattr(self, "_db", None)
        if db is not None:
            with contextlib.suppress(sqlite3.Error):
                db.close()
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    def _open_schema(self, *, migrate: bool) -> None:
        """Create the tables of a new spool, migrate one of schema 1, refuse any other."""
        db = self._db
        has_meta = db.execute(
            "SELECT 1 FROM sqlite_master WHERE type='table' AND name='meta'"
        ).fetchone()
        row = (
            db.execute("SELECT value FROM meta WHERE key='schema'").fetchone() if has_meta else None
        )
        if row is not None and row[0] == "1":
            if not migrate:
                raise SpoolError(
                    f"{self.path}: spool schema 1; start this version's gateway on it once to "
                    f"migrate it to schema {_SCHEMA_VERSION}"
                )
            self._migrate_v1()
            return
        if row is not None and row[0] != _SCHEMA_VERSION:
            raise SpoolError(
                f"{self.path}: spool schema {row[0]}, this gateway reads {_SCHEMA_VERSION}"
            )
        db.executescript(_SCHEMA)
        if row is None:
            db.execute("INSERT INTO meta VALUES ('schema', ?)", (_SCHEMA_VERSION,))

    def _migrate_v1(self) -> None:
        """Schema 1 -> 2 in one transaction: each event's ``pending`` rows become its owed bits.

        A kill -9 during it leaves schema 1 as it was (the next start migrates again).
        """
        db = self._db
        started = time.monotonic()
        db.execute("BEGIN IMMEDIATE")
        try:
            names = [str(r[0]) for r in db.execute("SELECT DISTINCT sink FROM pending ORDER BY 1")]
            if len(names) > MAX_SINKS:
                raise SpoolError(
                    f"{self.path}: schema 1 spool owes events to {len(names)} sinks; schema "
                    f"{_SCHEMA_VERSION} holds at most {MAX_SINKS}"
                )
            for statement in _SCHEMA.split(";"):
                if "CREATE TABLE IF NOT EXISTS events" not in statement and statement.strip():
                    db.execute(statement)
            db.executemany("INSERT INTO sinks (bit, name) VALUES (?, ?)", enumerate(names))
            db.execute("ALTER TABLE events ADD COLUMN owed INTEGER NOT NULL DEFAULT 0")
            db.execute(
                "UPDATE events SET owed = (SELECT coalesce(sum(1 << s.bit), 0) FROM pending p"
                " JOIN sinks s ON s.name = p.sink WHERE p.seq = events.seq)"
            )
            orphans = db.execute("DELETE FROM events WHERE owed = 0").rowcount
            owed = dict(db.execute("SELECT sink, count(*) FROM pending GROUP BY sink").fetchall())
            db.execute("DROP TABLE pending")
            db.execute("UPDATE meta SET value=? WHERE key='schema'", (_SCHEMA_VERSION,))
            db.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                db.execute("ROLLBACK")
            raise
        log.info(
            "spool_migrated",
            path=str(self.path),
            schema_from="1",
            schema_to=_SCHEMA_VERSION,
            pending=owed,
            events_owed_to_none=max(orphans, 0),
            seconds=round(time.monotonic() - started, 3),
        )

    def _checkpoint_rest(self) -> None:
        """A PASSIVE checkpoint on this connection: the pages the worker's did not copy."""
        if not self._db.in_transaction:
            self._db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()

    def _checkpoint_now(self) -> None:
        """A blocking checkpoint on this connection, the log emptied (the WAL past its bound)."""
        if not self._db.in_transaction:
            self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")

    def _load_bits(self) -> None:
        """The sinks' bits as committed (again after a group that did not commit)."""
        rows = self._db.execute("SELECT name, bit FROM sinks").fetchall()
        self._bits = {str(name): int(bit) for name, bit in rows}
        self._masks = {}

    def _mask(self, sinks: Sequence[str]) -> int:
        """The owed bits of ``sinks``, new sinks given a bit (inside the open transaction)."""
        key = tuple(sinks)
        mask = self._masks.get(key)
        if mask is None:
            mask = 0
            for sink in key:
                mask |= 1 << self._bit(sink, key)
            self._masks[key] = mask
        return mask

    def _bit(self, sink: str, keep: tuple[str, ...]) -> int:
        bit = self._bits.get(sink)
        if bit is not None:
            return bit
        free = set(range(MAX_SINKS)) - set(self._bits.values())
        if not free:  # a sink owed nothing (no longer configured) gives its bit up
            idle = sorted(
                (b, n)
                for n, b in self._bits.items()
                if self._pending.get(n, 0) <= 0 and n not in keep
            )
            if not idle:
                raise SpoolError(
                    f"spool {self._where}: events are owed to {MAX_SINKS} sinks already; "
                    f"cannot hold events for sink {sink!r}"
                )
            bit, gone = idle[0]
            self._db.execute("DELETE FROM sinks WHERE bit=?", (bit,))
            del self._bits[gone]
            self._masks = {}
            free = {bit}
        bit = min(free)
        self._db.execute("INSERT INTO sinks (bit, name) VALUES (?, ?)", (bit, sink))
        self._bits[sink] = bit
        return bit

    def _measure(self) -> int:
        db = self._db
        page = int(db.execute("PRAGMA page_size").fetchone()[0])
        used = int(db.execute("PRAGMA page_count").fetchone()[0])
        free = int(db.execute("PRAGMA freelist_count").fetchone()[0])
        return (used - free) * page

    @property
    def size_bytes(self) -> int:
        """Bytes in use (pages holding data), as last measured."""
        return self._bytes

    @property
    def is_full(self) -> bool:
        """True while the spool is at its cap: new durable events are refused."""
        return self._bytes >= self.max_bytes

    @property
    def refused(self) -> int:
        """Events refused because the spool was full, since start."""
        return self._refused

    def close(self) -> None:
        """Commit what is open, stop the checkpoints and close the database."""
        if self.checkpointer is not None:
            self.checkpointer.stop()
        with contextlib.suppress(sqlite3.Error):
            if self._group is not None:
                self._end(self._group, commit=True)
            elif self._db.in_transaction:
                self._db.execute("COMMIT")
        self._db.close()
        if self._lock is not None:
            self._lock.close()  # releases the flock

    # -- writing: one group commit per loop pass (``gateway.spool.group``) ---------------

    @property
    def open_group(self) -> Commit | None:
        """The group of writes not committed yet, None if every write is committed."""
        return self._group

    def group(self) -> Commit:
        """The open group commit, opened now if there is none.

        Opened outside ``batch()`` with an event loop running, it commits at the end of the
        current loop pass (``Commit.scheduled``); otherwise its owner ends it (``flush``, or
        the end of the ``batch()`` scope). ``SpoolError`` if the spool cannot begin one.
        """
        try:
            return self._group or self._begin()
        except sqlite3.Error as exc:
            raise SpoolError(f"spool {self._where}: {exc}") from exc

    def _begin(self) -> Commit:
        try:
            self._db.execute("BEGIN IMMEDIATE")
        except sqlite3.Error as exc:
            self.commits.failed(exc)
            raise
        group = self._group = Commit()
        if not self._scopes and self._owner:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:
                return group  # no loop (a command, a plain test): its owner ends it
            loop.call_soon(self._end_of_pass, group)
            group.scheduled = True
        return group

    def _end_of_pass(self, group: Commit) -> None:
        if self._group is not group or self._scopes:
            return
        if not (group.has_appends or group.waited_on or group.lingered):
            # Confirmations alone, no one waiting: the other runners of the same publish may
            # confirm in the next passes (a sink that hops to a thread); one commit for all.
            group.lingered = group.lingering = True
            group.on_hurry = self._hurry
            asyncio.get_running_loop().call_later(SETTLE_LINGER_S, self._end_of_pass, group)
            return
        self._end(group, commit=True)

    def _hurry(self, group: Commit) -> None:
        asyncio.get_running_loop().call_soon(self._end_of_pass, group)

    def flush(self) -> bool:
        """Commit the open group now (unless a ``batch()`` scope holds it); False if it failed.

        A group that fails to commit is rolled back: its events are never sent
        (``rolled_back``), and those who asked hear it (``Commit.when_done``).
        """
        group = self._group
        if group is None or self._scopes:
            return True
        return self._end(group, commit=True) is None

    def _write_rows(self, group: Commit) -> None:
        """Write the rows ``group`` holds back (its appends); raises ``sqlite3.Error``."""
        if group.events:
            events, group.events = group.events, []
            self._db.executemany(
                "INSERT INTO events (seq, event_id, kind, body, spooled_at, owed)"
                " VALUES (?, ?, ?, ?, ?, ?)",
                events,
            )

    def _drain(self) -> None:
        """Before a read: the open group's appends written (a failure rolls the group back)."""
        group = self._group
        if group is None or not group.events:
            return
        try:
            self._write_rows(group)
        except sqlite3.Error as exc:
            if not self._scopes:
                self._end(group, commit=False, cause=exc)
            raise SpoolError(f"spool {self._where}: {exc}") from exc

    def _end(
        self, group: Commit, *, commit: bool, cause: BaseException | None = None
    ) -> sqlite3.Error | None:
        """Commit or roll back ``group``; the SQLite error if it did not commit (None if it did)."""
        self._group = None
        error: sqlite3.Error | None = None
        if commit:
            try:
                self._write_rows(group)
                if group.confirmed:
                    self._db.executemany(
                        "DELETE FROM events WHERE seq=? AND owed=0",
                        [(seq,) for seq in group.confirmed],
                    )
                self._db.execute("COMMIT")
            except sqlite3.Error as exc:
                error = exc
                self.commits.failed(exc)
                with contextlib.suppress(sqlite3.Error):
                    self._db.execute("ROLLBACK")
        else:
            error = self._rollback(cause)
        if error is None and commit:
            self.commits.succeeded()
            if self.checkpointer is not None:
                self.checkpointer.committed()
            group.end(True)
            return None
        self._undo(group)
        group.end(False)
        return error or sqlite3.OperationalError("rolled back")

    def _undo(self, group: Commit) -> None:
        """``group`` did not commit: what it appended is not held, and must not be sent."""
        for seq, _ in group.appended:
            self.rolled_back.add(seq)
        self._pending.subtract(group.owed)
        with contextlib.suppress(sqlite3.Error):
            self._load_bits()  # a sink given a bit in it has none
        if len(self.rolled_back) > _ROLLED_BACK_KEEP:
            self.rolled_back = set(sorted(self.rolled_back)[-_ROLLED_BACK_KEEP // 2 :])
        with contextlib.suppress(sqlite3.Error):
            self._bytes = self._measure()
            self._dead = int(self._db.execute("SELECT count(*) FROM dead_letters").fetchone()[0])
            self._seen_rows = int(self._db.execute("SELECT count(*) FROM seen").fetchone()[0])

    def _rollback(self, exc: BaseException | None) -> sqlite3.Error:
        """Roll the open transaction back; count it if SQLite failed (directly or under ours)."""
        cause = exc if isinstance(exc, sqlite3.Error) else getattr(exc, "__cause__", None)
        if isinstance(cause, sqlite3.Error):
            self.commits.failed(cause)
        with contextlib.suppress(sqlite3.Error):
            self._db.execute("ROLLBACK")
            self._load_bits()  # a sink given a bit in it has none
        return (
            cause if isinstance(cause, sqlite3.Error) else sqlite3.OperationalError("rolled back")
        )

    def _owe(self, sink: str, count: int) -> None:
        """Change what the spool owes ``sink`` by ``count``, undone with an uncommitted group."""
        self._pending[sink] += count
        if self._group is not None:
            self._group.owed[sink] += count

    @contextlib.contextmanager
    def batch(self) -> Iterator[None]:
        """One transaction for everything written inside (no ``await`` in between).

        It joins the loop pass's group if one is open, and commits it when the outermost
        scope ends (``SpoolError`` if that fails); an exception inside rolls it all back.
        """
        self._scopes += 1
        try:
            group = self.group()
        except BaseException:
            self._scopes -= 1
            raise
        try:
            yield
        except BaseException as exc:
            self._scopes -= 1
            if not self._scopes and self._group is group:
                self._end(group, commit=False, cause=exc)
            raise
        self._scopes -= 1
        if not self._scopes and self._group is group:
            error = self._end(group, commit=True)
            if error is not None:
                raise SpoolError(f"spool {self._where}: {error}") from error

    @contextlib.contextmanager
    def _write(self, *, drain: bool = True) -> Iterator[sqlite3.Connection]:
        """A write joining the open group (opened now with a loop running), else committed at once.

        A write that fails inside a group rolls the group back (outside ``batch()``; inside,
        the scope does), so the group commits all of its writes or none.
        """
        group = self._group
        if group is None and self._owner and _loop_running():
            group = self._begin()
        if group is not None:
            try:
                if drain:  # not needed by a write of the ``seen`` table alone
                    self._write_rows(group)
                yield self._db
            except BaseException as exc:
                if not self._scopes and self._group is group:
                    self._end(group, commit=False, cause=exc)
                raise
            return
        if self._db.in_transaction:
            yield self._db
            return
        try:
            self._db.execute("BEGIN IMMEDIATE")
        except sqlite3.Error as exc:
            self.commits.failed(exc)
            raise
        try:
            yield self._db
        except BaseException as exc:
            self._rollback(exc)
            raise
        try:
            self._db.execute("COMMIT")
        except sqlite3.Error as exc:
            self.commits.failed(exc)
            with contextlib.suppress(sqlite3.Error):
                self._db.execute("ROLLBACK")
                self._load_bits()
            raise
        self.commits.succeeded()
        if self.checkpointer is not None:
            self.checkpointer.committed()

    def writing(self) -> contextlib.AbstractContextManager[sqlite3.Connection]:
        """A write of a table kept beside the spool's (``gateway.spool.orderbook``): it joins the
        open group commit like the spool's own writes (committed at once without a loop)."""
        return self._write()

    def read(self, sql: str, params: Sequence[object] = ()) -> list[tuple[object, ...]]:
        """The rows of one query of a table kept beside the spool's."""
        try:
            return [tuple(row) for row in self._db.execute(sql, params).fetchall()]
        except sqlite3.Error as exc:
            raise SpoolError(f"spool {self._where}: {exc}") from exc

    def probe(self) -> bool:
        """One small write, to learn whether writes commit again after failing; True if so."""
        try:
            with self._write() as db:
                db.execute(
                    "INSERT OR REPLACE INTO meta VALUES ('probed_at', ?)", (str(time.time()),)
                )
        except (sqlite3.Error, SpoolError):
            return False
        return self.flush()

    def append(self, event: Event, sinks: Sequence[str]) -> int | None:
        """Hold ``event`` for ``sinks``; its ``seq``, or None if the spool is full.

        Raises ``SpoolError`` if the database cannot be written (disk full, I/O error).
        """
        if self._bytes >= self.max_bytes:
            self._appends += 1
            if self._appends % _SIZE_CHECK_EVERY == 0:
                # Durable events come before de-duplication memory: the oldest detection
                # ids make room first (a re-send of one of them is delivered again, and its
                # receivers drop it by event id).
                self._prune_seen(force=True)
                self._bytes = self._measure()
            if self._bytes >= self.max_bytes:
                self._refuse(event)
                return None
        body = event.model_dump_json().encode()
        try:
            group = self._group
            if group is None and self._owner and _loop_running():
                group = self._begin()
            if group is None:
                seq = self._insert(event.event_id, event.kind.value, body, time.time(), sinks)
            else:  # written with the rest of the group's appends (``_write_rows``)
                mask = self._masks.get(sinks) if type(sinks) is tuple else None
                if mask is None:
                    mask = self._mask(sinks)
                seq = self._seq = self._seq + 1
                group.events.append(
                    (seq, event.event_id, event.kind.value, body, time.time(), mask)
                )
                group.appended.append((seq, tuple(sinks)))
                if group.lingering:
                    group.hurry()  # an event: committed at the end of this pass
                owed = group.owed
                for sink in sinks:  # not Counter.update: its Mapping check costs more here
                    owed[sink] += 1
        except sqlite3.Error as exc:
            raise SpoolError(f"spool {self._where}: {exc}") from exc
        pending = self._pending
        for sink in sinks:
            pending[sink] += 1
        self._appends += 1
        self._bytes += len(body) + 64
        if self._appends % _SIZE_CHECK_EVERY == 0:
            self._bytes = self._measure()
        if self._bytes >= self.warn_bytes and self._warn_log.allow("warn"):
            log.warning(
                "spool_nearly_full",
                size_bytes=self._bytes,
                max_bytes=self.max_bytes,
                pending=dict(self._pending),
                note="new durable events are refused at max_bytes: check the sinks",
            )
        return seq

    def _insert(
        self, event_id: str, kind: str, body: bytes, spooled_at: float, sinks: Sequence[str]
    ) -> int:
        seq = self._seq + 1
        with self._write() as db:
            db.execute(
                "INSERT INTO events (seq, event_id, kind, body, spooled_at, owed)"
                " VALUES (?, ?, ?, ?, ?, ?)",
                (seq, event_id, kind, body, spooled_at, self._mask(sinks)),
            )
        self._seq = seq
        return seq

    def _refuse(self, event: Event) -> None:
        self._refused += 1
        if self._full_log.allow("full"):
            log.error(
                "spool_full",
                size_bytes=self._bytes,
                max_bytes=self.max_bytes,
                refused_total=self._refused,
                kind=event.kind.value,
                pending=dict(self._pending),
                note="durable events are refused; detections stay unacknowledged on the airframes",
            )

    def seen(self, event_id: str) -> bool:
        """True if a detection with this id was taken in within the de-duplication window."""
        row = self._db.execute("SELECT at FROM seen WHERE event_id=?", (event_id,)).fetchone()
        return row is not None and time.time() - float(row[0]) < self.dedup_window_s

    def remember(self, event_id: str) -> None:
        """Record a detection id as taken in (in the open batch, with its event)."""
        with self._write(drain=False) as db:
            db.execute("INSERT OR REPLACE INTO seen VALUES (?, ?)", (event_id, time.time()))
        self._seen_rows += 1
        if self._seen_rows % _SEEN_PRUNE_EVERY == 0 or self._seen_rows > self.seen_max:
            self._prune_seen()

    def _prune_seen(self, *, force: bool = False) -> None:
        """Forget detection ids past the window, and the oldest beyond ``seen_max``.

        At most ``_SEEN_PRUNE_CHUNK`` rows per call, so a large backlog never holds the event
        loop long; ``force`` drops the oldest chunk even inside the window (a full spool).
        """
        cutoff = time.time() - self.dedup_window_s
        with self._write(drain=False) as db:
            cursor = db.execute(
                "DELETE FROM seen WHERE event_id IN "
                "(SELECT event_id FROM seen WHERE at < ? LIMIT ?)",
                (cutoff, _SEEN_PRUNE_CHUNK),
            )
            removed = max(cursor.rowcount, 0)
            if force or self._seen_rows - removed > self.seen_max:
                cursor = db.execute(
                    "DELETE FROM seen WHERE event_id IN "
                    "(SELECT event_id FROM seen ORDER BY at LIMIT ?)",
                    (_SEEN_PRUNE_CHUNK,),
                )
                removed += max(cursor.rowcount, 0)
        self._seen_rows = max(self._seen_rows - removed, 0)

    def confirm(self, sink: str, seqs: Iterable[int]) -> None:
        """``sink`` has delivered these events: they are no longer owed to it."""
        self._settle(sink, list(seqs))

    def _settle(self, sink: str, seqs: list[int]) -> None:
        bit = self._bits.get(sink)
        if not seqs or bit is None:  # no bit: nothing was ever owed to it
            return
        flag = 1 << bit
        try:
            with self._write() as db:
                cursor = db.executemany(
                    "UPDATE events SET owed = owed & ? WHERE seq=? AND owed & ? != 0",
                    [(~flag, s, flag) for s in seqs],
                )
                self._owe(sink, -max(cursor.rowcount, 0))
                if self._group is not None:
                    self._group.confirmed.update(seqs)  # deleted once, at the commit
                else:
                    db.executemany(
                        "DELETE FROM events WHERE seq=? AND owed=0", [(s,) for s in seqs]
                    )
            # Measured, not estimated, as it shrinks while near the cap: a drained spool must
            # stop being "full" (and stop its alerts) without waiting for new appends.
            self._settles += 1
            if self._bytes >= self.warn_bytes or self._settles % _SIZE_CHECK_EVERY == 0:
                self._bytes = self._measure()
        except sqlite3.Error as exc:
            raise SpoolError(f"spool {self.path or ':memory:'}: {exc}") from exc

    def dead_letter(self, sink: str, seqs: Sequence[int], reason: str) -> None:
        """Move these events of ``sink`` to the dead letters, with ``reason``."""
        if not seqs:
            return
        now = time.time()
        with self._write() as db:
            db.executemany(
                "INSERT INTO dead_letters (sink, event_id, kind, body, reason, spooled_at, dead_at)"
                " SELECT ?, event_id, kind, body, ?, spooled_at, ? FROM events WHERE seq=?",
                [(sink, reason[:1000], now, seq) for seq in seqs],
            )
            self._dead = int(db.execute("SELECT count(*) FROM dead_letters").fetchone()[0])
            over = self._dead
            if over > self.dead_letters_max:
                db.execute(
                    "DELETE FROM dead_letters WHERE id IN "
                    "(SELECT id FROM dead_letters ORDER BY id LIMIT ?)",
                    (over - self.dead_letters_max,),
                )
                self._dead = self.dead_letters_max
            self._settle(sink, list(seqs))

    # -- reading ---------------------------------------------------------------------------

    def pending(self, sink: str, *, after: int = 0, limit: int = 1000) -> list[Spooled]:
        """Up to ``limit`` events owed to ``sink`` with ``seq`` above ``after``, in order.

        A row whose body no longer parses (written by another version) is dead-lettered with
        the reason instead of stopping the sink.
        """
        self._drain()
        bit = self._bits.get(sink)
        if bit is None:
            return []
        # The primary key from ``after`` on, skipping what only other sinks are owed.
        rows = self._db.execute(
            "SELECT seq, body, spooled_at FROM events WHERE seq>? AND owed & ? != 0"
            " ORDER BY seq LIMIT ?",
            (after, 1 << bit, limit),
        ).fetchall()
        out: list[Spooled] = []
        for seq, body, spooled_at in rows:
            try:
                event = event_adapter.validate_json(body)
            except ValueError as exc:
                self.dead_letter(sink, [seq], f"unreadable in the spool: {exc}"[:1000])
                continue
            out.append(Spooled(int(seq), event, float(spooled_at)))
        return out

    def pending_count(self, sink: str) -> int:
        """Events owed to ``sink``."""
        return self._pending.get(sink, 0)

    def recount(self, sink: str) -> int:
        """What ``sink`` is owed, as the database has it.

        The gateway that holds the file keeps the count as it writes (no other process
        writes owed events: the ``spool`` command only marks dead letters, which the gateway
        moves), so for it this is the count kept, with no scan of the table; another
        process counts from the file.
        """
        if self._owner:
            return self._pending.get(sink, 0)
        self._drain()
        self._load_bits()
        bit = self._bits.get(sink)
        count = 0
        if bit is not None:
            row = self._db.execute("SELECT count(*) FROM events WHERE owed & ? != 0", (1 << bit,))
            count = int(row.fetchone()[0])
        self._pending[sink] = count
        return count

    def pending_counts(self) -> dict[str, int]:
        """Events owed, per sink (sinks no longer configured included)."""
        return {sink: n for sink, n in self._pending.items() if n > 0}

    def dead_letters(self, sink: str | None = None, *, limit: int = 1000) -> list[DeadLetter]:
        """The newest dead letters (of ``sink``), newest first."""
        query = "SELECT id, sink, event_id, kind, reason, spooled_at, dead_at FROM dead_letters"
        args: tuple[object, ...] = ()
        if sink is not None:
            query += " WHERE sink=?"
            args = (sink,)
        query += " ORDER BY id DESC LIMIT ?"
        rows = self._db.execute(query, (*args, limit)).fetchall()
        return [DeadLetter(*row) for row in rows]

    def dead_letter_count(self) -> int:
        """Dead letters held."""
        return self._dead

    def dead_letters_of(self, sink: str) -> int:
        """Dead letters held for ``sink``; ``SpoolError`` once the spool is closed."""
        try:
            row = self._db.execute("SELECT count(*) FROM dead_letters WHERE sink=?", (sink,))
            return int(row.fetchone()[0])
        except sqlite3.Error as exc:
            raise SpoolError(f"spool {self.path or ':memory:'}: {exc}") from exc

    def dead_letter_by_id(self, letter_id: int) -> DeadLetter | None:
        """One dead letter, None if there is no such letter."""
        row = self._db.execute(
            "SELECT id, sink, event_id, kind, reason, spooled_at, dead_at FROM dead_letters"
            " WHERE id=?",
            (letter_id,),
        ).fetchone()
        return None if row is None else DeadLetter(*row)

    def dead_letter_body(self, letter_id: int) -> bytes | None:
        """The event JSON of one dead letter, None if there is no such letter."""
        row = self._db.execute("SELECT body FROM dead_letters WHERE id=?", (letter_id,)).fetchone()
        return None if row is None else bytes(row[0])

    def requeue(self, ids: Iterable[int] | None = None, *, sink: str | None = None) -> int:
        """Mark dead letters for re-queueing (all of ``sink``'s, or all, if ``ids`` is None).

        How many were marked. The gateway that owns the spool moves them back into their
        sink's queue (last in order) at its next ``take_requeued``; called by that gateway
        itself, they are moved at once.
        """
        marked = 0
        with self._write() as db:
            if ids is None and sink is None:
                cursor = db.execute("UPDATE dead_letters SET requeue=1 WHERE requeue=0")
                marked = max(cursor.rowcount, 0)
            elif ids is None:
                cursor = db.execute(
                    "UPDATE dead_letters SET requeue=1 WHERE requeue=0 AND sink=?", (sink,)
                )
                marked = max(cursor.rowcount, 0)
            else:
                for letter_id in sorted(set(ids)):
                    query = "UPDATE dead_letters SET requeue=1 WHERE id=?"
                    args: tuple[object, ...] = (letter_id,)
                    if sink is not None:
                        query += " AND sink=?"
                        args = (letter_id, sink)
                    marked += max(db.execute(query, args).rowcount, 0)
        if self._owner:
            self.take_requeued()
        return marked

    def take_requeued(self) -> int:
        """Move dead letters marked for re-queueing back into their sinks' queues; how many."""
        rows = self._db.execute(
            "SELECT id, sink, event_id, kind, body FROM dead_letters WHERE requeue=1 ORDER BY id"
        ).fetchall()
        if not rows:
            return 0
        now = time.time()
        with self._write() as db:
            for letter_id, letter_sink, event_id, kind, body in rows:
                self._insert(event_id, kind, body, now, (letter_sink,))
                db.execute("DELETE FROM dead_letters WHERE id=?", (letter_id,))
                self._owe(letter_sink, 1)
        self._dead = int(self._db.execute("SELECT count(*) FROM dead_letters").fetchone()[0])
        log.info("spool_requeued", count=len(rows))
        return len(rows)
