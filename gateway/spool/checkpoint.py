"""The spool's WAL checkpoints, made from a worker thread instead of a commit on the event loop.

SQLite copies the write-ahead log's pages into the database file at a *checkpoint*, with an
fsync of the file. By default the commit that takes the log past 1,000 pages makes one,
there and then: on the event loop, a stall of milliseconds to tens of them every few hundred
commits (a p99 of delivery). The gateway's own spool connection therefore runs with
``wal_autocheckpoint=0``, and ``Checkpointer`` makes the checkpoints:

- a worker thread on a connection of its own runs ``PRAGMA wal_checkpoint(PASSIVE)`` every
  ``interval_s``, and sooner once ``NUDGE_COMMITS`` commits were made since the last one.
  PASSIVE takes no lock that a commit waits for: the loop's commits go on meanwhile, and
  SQLite's C code runs without Python's GIL;
- the log starts over from its beginning at the first write after a checkpoint that copied
  all of it, and the file is then cut back to ``soft_bytes`` (the spool's connection sets it
  as ``journal_size_limit``). Between bursts of commits the worker catches up and that is
  what happens. Under commits without a pause it does not by itself: the worker copies what
  was there when it began, and the next commits are in the log before it ends, so the log
  would grow. So once the worker has copied all it found and the log is past ``soft_bytes``,
  the loop's next commit *finishes* it (``finish``, PASSIVE on the loop's connection): it
  copies only the pages of the commits made since the worker began, syncs, and the commit
  after it starts the log over (issue #24: at 4,900 detections/s about 8 finishes a second,
  0.9 ms each with their fsyncs, 2.2 ms at most, and the WAL stays near 4 MiB; before, it
  reached 64 MiB every 2-3 s and its blocking checkpoint stalled the loop 23-33 ms).
  Past ``hard_bytes`` (a worker that fell behind) the commit that finds it so makes a
  blocking checkpoint (TRUNCATE) on the loop's connection.

Durability is the spool's (``gateway.spool.store``): a commit is durable against kill -9 when
it returns, whether its pages are still in the log or already copied; a checkpoint only
copies committed pages, so a crash during one loses nothing (the log is replayed at the next
open). A longer log costs a longer replay at start, bounded by ``hard_bytes``.
"""

from __future__ import annotations

import os
import sqlite3
import threading
import time
from collections.abc import Callable
from pathlib import Path

import structlog

from gateway.ops.logsetup import RateLimit
from gateway.spool.commits import failure_reason

__all__ = ["NUDGE_COMMITS", "WAL_HARD_BYTES", "WAL_SOFT_BYTES", "Checkpointer"]

log = structlog.get_logger(__name__)

#: What the WAL file is cut back to when the log starts over (SQLite's own default is 1,000
#: pages before a checkpoint: 4 MiB).
WAL_SOFT_BYTES = 4 << 20
#: Past this, a commit on the loop checkpoints itself (blocking).
WAL_HARD_BYTES = 64 << 20
#: Commits after which the worker is woken before its interval.
NUDGE_COMMITS = 32
#: Commits between two looks at the WAL file's size (one ``stat``).
_SIZE_EVERY = 64
#: Bytes of a WAL frame's header, before its page.
_FRAME_HEADER = 24
_LOG_INTERVAL_S = 60.0


class Checkpointer:
    """PASSIVE checkpoints of one spool file from a worker thread, and the blocking fallback.

    ``blocking`` gives the blocking checkpoint to make on the caller's thread (None once the
    spool is gone: a ``weakref.WeakMethod``, so the worker does not keep its spool alive);
    ``finish``, likewise, the PASSIVE checkpoint that copies the rest after a complete one of
    the worker's (None: the log is left to ``hard_bytes``).
    """

    def __init__(
        self,
        path: Path,
        blocking: Callable[[], Callable[[], None] | None],
        *,
        finish: Callable[[], Callable[[], None] | None] | None = None,
        interval_s: float = 0.5,
        soft_bytes: int = WAL_SOFT_BYTES,
        hard_bytes: int = WAL_HARD_BYTES,
    ) -> None:
        self.path = path
        self.wal = Path(f"{path}-wal")
        self.interval_s = interval_s
        self.soft_bytes = soft_bytes
        self.hard_bytes = hard_bytes
        self._blocking = blocking
        self._finish = finish
        #: Set by the worker after a checkpoint that copied the whole log past ``soft_bytes``.
        self._finish_due = False
        self._wake = threading.Event()
        #: Held by whoever checkpoints: the loop's blocking checkpoint waits for the worker's
        #: in progress instead of finding SQLite busy and trying again 64 commits later.
        self._checkpointing = threading.Lock()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._since = 0  # commits since the worker was last woken
        self._counted = 0  # commits since the last look at the WAL's size
        #: PASSIVE checkpoints made by the worker, and those SQLite found busy.
        self.passive = 0
        self.busy = 0
        #: Blocking checkpoints made on the loop (the WAL past ``hard_bytes``), and the longest.
        self.blocking = 0
        self.longest_blocking_s = 0.0
        #: Checkpoints that failed (the worker's, with an error).
        self.failures = 0
        #: Worker checkpoints finished on the loop (the log could then start over).
        self.finished = 0
        #: Frames in the log and frames copied, at the worker's last checkpoint.
        self.last: tuple[int, int] = (0, 0)
        self._log = RateLimit(interval_s=_LOG_INTERVAL_S)

    def start(self) -> None:
        """Start the worker thread (once)."""
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._run, name=f"spool-checkpoint {self.path.name}", daemon=True
            )
            self._thread.start()

    def halt(self) -> None:
        """Tell the worker to stop, without waiting for it."""
        self._stopping = True
        self._wake.set()

    def stop(self) -> None:
        """Stop the worker and wait for its checkpoint in progress, if any, to end."""
        self.halt()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def committed(self) -> None:
        """A commit was made on the loop: finish the worker's checkpoint if it is due, wake
        the worker now and then; bound the WAL."""
        if self._finish_due:
            self.finish()
        self._since += 1
        if self._since >= NUDGE_COMMITS:
            self._since = 0
            self._wake.set()
        self._counted += 1
        if self._counted >= _SIZE_EVERY:
            self._counted = 0
            self.bound()

    def finish(self) -> None:
        """Copy what was committed since the worker's complete checkpoint (on the caller's
        thread, between transactions), so that the next commit starts the log over.

        Skipped while the worker checkpoints (tried again at the next commit): the loop never
        waits for it here.
        """
        finish = self._finish() if self._finish is not None else None
        if finish is None or not self._checkpointing.acquire(blocking=False):
            return
        self._finish_due = False
        try:
            finish()
        except sqlite3.Error as exc:
            self.failures += 1
            if self._log.allow(("failed", failure_reason(exc))):
                log.warning("spool_checkpoint_failed", error=str(exc)[:300], blocking=False)
            return
        finally:
            self._checkpointing.release()
        self.finished += 1

    def bound(self) -> bool:
        """Checkpoint on the caller's thread (blocking) if the WAL is past ``hard_bytes``."""
        try:
            size = os.stat(self.wal).st_size
        except OSError:
            return False
        if size < self.hard_bytes:
            return False
        checkpoint = self._blocking()
        if checkpoint is None:  # the spool is gone
            return False
        self.blocking += 1
        started = time.perf_counter()
        try:
            with self._checkpointing:
                checkpoint()
        except sqlite3.Error as exc:
            self.failures += 1
            if self._log.allow(("failed", failure_reason(exc))):
                log.error("spool_checkpoint_failed", error=str(exc)[:300], blocking=True)
            return True
        seconds = time.perf_counter() - started
        self.longest_blocking_s = max(self.longest_blocking_s, seconds)
        if self._log.allow("blocking"):
            log.info(
                "spool_checkpoint_blocking",
                wal_bytes=size,
                hard_bytes=self.hard_bytes,
                seconds=round(seconds, 4),
                blocking_total=self.blocking,
                note="commits without a pause: the WAL was checkpointed and emptied on the "
                "event loop (logged at most once a minute)",
            )
        return True

    def _run(self) -> None:
        try:
            db = sqlite3.connect(self.path, isolation_level=None, timeout=0.0)
        except sqlite3.Error as exc:
            log.error(
                "spool_checkpoint_unavailable",
                error=str(exc)[:300],
                note="checkpoints are made on the event loop past the WAL's hard limit",
            )
            return
        try:
            page = int(db.execute("PRAGMA page_size").fetchone()[0])
            while self._live():
                self._wake.wait(self.interval_s)
                self._wake.clear()
                if self._live():
                    self._checkpoint(db, page)
        finally:
            db.close()

    def _live(self) -> bool:
        return not self._stopping

    def _checkpoint(self, db: sqlite3.Connection, page: int) -> None:
        try:
            with self._checkpointing:
                busy, frames, copied = db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
        except sqlite3.Error as exc:
            self.failures += 1
            if self._log.allow(("failed", failure_reason(exc))):
                log.warning("spool_checkpoint_failed", error=str(exc)[:300], blocking=False)
            return
        self.passive += 1
        if busy:
            self.busy += 1
        self.last = (int(frames), int(copied))
        if not busy and frames == copied and frames * (page + _FRAME_HEADER) > self.soft_bytes:
            self._finish_due = True  # read by the loop's next commit (a bool: no lock needed)
