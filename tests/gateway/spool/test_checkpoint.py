"""WAL checkpoints of the spool off the event loop (``gateway.spool.checkpoint``).

No durations are asserted: what is checked is who checkpoints (the worker's connection, not a
commit of the loop's) and that the log stays bounded when the worker does not keep up.
"""

from __future__ import annotations

import gc
import os
import sqlite3
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

from gateway.events import Detection, Position, Sensor
from gateway.spool.checkpoint import Checkpointer
from gateway.spool.store import Spool

T0 = datetime(2026, 11, 23, 12, 0, tzinfo=UTC)


def detection(n: int) -> Detection:
    return Detection(
        event_id=f"det-{n}",
        airframe="F26E-001",
        time=T0,
        sensor=Sensor.EO,
        object_class="tank",
        subtype="x" * 2000,  # a page of WAL or so per commit
        confidence=0.9,
        position=Position(lat_deg=58.4, lon_deg=15.6),
        sigma_h_m=8.0,
    )


def commit_events(spool: Spool, first: int, count: int) -> None:
    for n in range(first, first + count):
        with spool.batch():
            spool.append(detection(n), ("a", "b"))


def wal_frames(path: Path) -> int:
    """Frames in the log, as a PASSIVE checkpoint of another connection reports them."""
    db = sqlite3.connect(path)
    try:
        db.execute("PRAGMA wal_autocheckpoint=0")
        return int(db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()[1])
    finally:
        db.close()


def checkpoint_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("spool-checkpoint")]


def test_commits_on_the_loop_never_checkpoint(tmp_path: Path) -> None:
    spool = Spool(tmp_path / "spool.db")
    assert spool._db.execute("PRAGMA wal_autocheckpoint").fetchone() == (0,)
    assert spool.checkpointer is not None
    spool.checkpointer.stop()  # only the loop's commits now
    commit_events(spool, 0, 1500)  # past SQLite's automatic checkpoint at 1,000 pages
    frames = wal_frames(tmp_path / "spool.db")
    assert frames > 1500  # every commit's pages still in the log: none was copied back
    spool.close()


def test_the_worker_checkpoints_and_the_log_starts_over(tmp_path: Path) -> None:
    path = tmp_path / "spool.db"
    spool = Spool(path)
    checkpointer = spool.checkpointer
    assert checkpointer is not None
    try:
        commit_events(spool, 0, 300)
        # Two more checkpoints of the worker's: the second began after the last commit.
        wanted = checkpointer.passive + 2
        deadline = time.monotonic() + 60  # a bound on waiting, not on the machine's speed
        while checkpointer.passive < wanted:
            assert time.monotonic() < deadline, "the worker made no checkpoint"
            checkpointer._wake.set()
            time.sleep(0.05)
        frames, copied = checkpointer.last
        assert frames == copied > 0  # every frame copied into the database
        commit_events(spool, 300, 5)
        assert wal_frames(path) < 300  # the commit after a complete checkpoint rewinds the log
        assert checkpointer.blocking == 0
    finally:
        spool.close()
    assert checkpoint_threads() == []
    reopened = Spool(path)
    assert reopened.pending_count("a") == 305
    reopened.close()


def test_a_commit_finishes_a_complete_checkpoint_and_the_log_starts_over(tmp_path: Path) -> None:
    """Commits without a pause: the worker copies all it found, more commits follow before
    the log could start over; the loop's next commit copies the rest, and the one after
    rewinds the log (issue #24: it used to grow to ``hard_bytes`` and stall the loop)."""
    path = tmp_path / "spool.db"
    spool = Spool(path)
    checkpointer = spool.checkpointer
    assert checkpointer is not None
    checkpointer.stop()  # the test plays the worker, at the moments it chooses
    checkpointer.soft_bytes = 64 << 10
    worker = sqlite3.connect(path, isolation_level=None)
    try:
        commit_events(spool, 0, 100)
        checkpointer._checkpoint(worker, 4096)  # the worker copies every frame there is
        assert checkpointer.last[0] == checkpointer.last[1] > 0
        assert checkpointer._finish_due
        commit_events(spool, 100, 1)  # committed before the log could start over; finishes
        assert checkpointer.finished == 1
        assert not checkpointer._finish_due
        commit_events(spool, 101, 1)  # the first commit after a complete checkpoint
        assert wal_frames(path) < 10
        assert checkpointer.blocking == 0
    finally:
        worker.close()
        spool.close()
    reopened = Spool(path)
    assert reopened.pending_count("a") == 102
    reopened.close()


def test_the_loop_does_not_wait_for_the_worker_to_finish(tmp_path: Path) -> None:
    """While the worker checkpoints, the finish is left to a later commit."""
    path = tmp_path / "spool.db"
    spool = Spool(path)
    checkpointer = spool.checkpointer
    assert checkpointer is not None
    checkpointer.stop()
    checkpointer._finish_due = True
    with checkpointer._checkpointing:  # the worker's checkpoint in progress
        commit_events(spool, 0, 1)
    assert checkpointer.finished == 0
    assert checkpointer._finish_due
    commit_events(spool, 1, 1)
    assert checkpointer.finished == 1
    spool.close()


def test_past_its_hard_limit_the_log_is_checkpointed_by_the_commit(tmp_path: Path) -> None:
    path = tmp_path / "spool.db"
    spool = Spool(path)
    assert spool.checkpointer is not None
    spool.checkpointer.stop()  # a worker that does not keep up
    hard = 512 << 10
    spool.checkpointer = Checkpointer(path, lambda: spool._checkpoint_now, hard_bytes=hard)
    biggest = 0
    for first in range(0, 1200, 100):
        commit_events(spool, first, 100)
        biggest = max(biggest, os.stat(f"{path}-wal").st_size)
    assert spool.checkpointer.blocking > 0
    # Bounded: at most the commits between two looks at the size past the limit.
    assert biggest < hard + 64 * 3 * 4096 * 2
    spool.close()
    reopened = Spool(path)
    assert reopened.pending_count("b") == 1200
    reopened.close()


def test_a_spool_dropped_unclosed_stops_its_worker(tmp_path: Path) -> None:
    spool = Spool(tmp_path / "spool.db")
    assert spool.checkpointer is not None
    thread = spool.checkpointer._thread
    assert thread is not None
    assert spool._lock is not None
    spool._lock.close()  # what close() would have freed; the rest is left to the collector
    spool._db.close()
    del spool
    gc.collect()
    thread.join(timeout=60)  # a bound on waiting, not on the machine's speed
    assert not thread.is_alive()
