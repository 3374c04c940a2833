"""The spool's check at start (the WAL, the database) and its record of failed commits.

A crash image is made the honest way: a real spool is written, and its database and ``-wal``
files are copied while it is still open (as kill -9 leaves them: no checkpoint at close).
Bytes of the copy's WAL are then damaged and the copy opened; SQLite's own count of the
frames it replayed (``PRAGMA wal_checkpoint``) is the reference for the scan's.
"""

from __future__ import annotations

import shutil
import sqlite3
from datetime import UTC, datetime
from pathlib import Path

import structlog

from gateway.errors import SpoolError
from gateway.events import Detection, Position, Sensor
from gateway.spool.startcheck import check_integrity
from gateway.spool.store import Spool
from gateway.spool.wal import scan_wal

PAGE = 4096
FRAME = 24 + PAGE


def detection(n: int) -> Detection:
    return Detection(
        event_id=f"det-{n}",
        airframe="F26E-001",
        time=datetime(2026, 11, 23, tzinfo=UTC),
        sensor=Sensor.EO,
        object_class="tank",
        confidence=0.9,
        position=Position(lat_deg=65.8, lon_deg=21.7),
        sigma_h_m=8.0,
    )


def write(spool: Spool, first: int, count: int) -> None:
    """``count`` datagrams of one detection each, as ingest commits them."""
    for n in range(first, first + count):
        with spool.batch():
            spool.append(detection(n), ("slb",))
            spool.remember(f"det-{n}")


def crash_image_of(spool: Spool, directory: Path) -> Path:
    """The files of the open ``spool`` copied to ``directory``, as kill -9 would leave them."""
    directory.mkdir()
    assert spool.path is not None
    for suffix in ("", "-wal"):
        shutil.copyfile(f"{spool.path}{suffix}", directory / f"spool.db{suffix}")
    return directory / "spool.db"


def crash_image(tmp_path: Path, datagrams: int = 60) -> Path:
    """A spool with ``datagrams`` commits in its WAL, as a killed gateway leaves it."""
    live = tmp_path / "live"
    live.mkdir()
    spool = Spool(live / "spool.db")
    write(spool, 0, datagrams)
    image = crash_image_of(spool, tmp_path / "image")
    spool.close()
    return image


def flip(path: Path, offset: int) -> None:
    with path.open("r+b") as handle:
        handle.seek(offset)
        byte = handle.read(1)
        handle.seek(offset)
        handle.write(bytes([byte[0] ^ 0xFF]))


def sqlite_replays(db_path: Path) -> int:
    """How many WAL frames SQLite itself takes from the file (its recovery's count)."""
    db = sqlite3.connect(db_path)
    try:
        return int(db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()[1])
    finally:
        db.close()


def held(path: Path) -> list[str]:
    db = sqlite3.connect(path)
    try:
        rows = db.execute("SELECT event_id FROM events ORDER BY seq").fetchall()
    finally:
        db.close()
    return [row[0] for row in rows]


class TestWalScan:
    """The scan says what SQLite will replay of a WAL, and what it will drop."""

    def test_an_intact_log_is_replayed_whole(self, tmp_path: Path) -> None:
        path = crash_image(tmp_path)
        scan = scan_wal(Path(f"{path}-wal"), page_size=PAGE)
        assert scan.frames > 60
        assert scan.replayed == scan.frames
        assert (scan.lost_frames, scan.lost_commits, scan.problem) == (0, 0, "")
        assert scan.commits >= 60
        assert sqlite_replays(path) == scan.replayed
        assert len(held(path)) == 60

    def test_a_damaged_frame_drops_every_commit_after_it(self, tmp_path: Path) -> None:
        path = crash_image(tmp_path)
        wal = Path(f"{path}-wal")
        whole = scan_wal(wal, page_size=PAGE)
        middle = whole.frames // 2
        flip(wal, 32 + (middle - 1) * FRAME + 24 + 1000)  # inside frame `middle`'s page
        scan = scan_wal(wal, page_size=PAGE)
        assert scan.problem == f"frame {middle} fails its checksum"
        assert scan.replayed < middle
        assert scan.lost_frames == whole.frames - scan.replayed
        assert scan.commits + scan.lost_commits == whole.commits
        assert scan.lost_commits > 10
        assert sqlite_replays(path) == scan.replayed  # SQLite agrees frame for frame
        events = held(path)
        assert events == [f"det-{n}" for n in range(len(events))]
        assert len(events) < 60  # what those commits held is gone

    def test_a_damaged_salt_in_the_first_frame_loses_the_whole_log(self, tmp_path: Path) -> None:
        path = crash_image(tmp_path, datagrams=5)
        wal = Path(f"{path}-wal")
        flip(wal, 32 + 8)  # frame 1's salt-1
        scan = scan_wal(wal, page_size=PAGE)
        assert scan.problem == "frame 1 carries other salts"
        assert (scan.replayed, scan.lost_frames) == (0, scan.frames)
        assert sqlite_replays(path) == 0

    def test_a_damaged_header_loses_the_whole_log(self, tmp_path: Path) -> None:
        path = crash_image(tmp_path, datagrams=5)
        wal = Path(f"{path}-wal")
        flip(wal, 20)  # the header's salt-2: its checksum fails
        scan = scan_wal(wal, page_size=PAGE)
        assert scan.problem.startswith("the header is damaged")
        assert scan.lost_frames == scan.frames > 0
        assert scan.lost_commits >= 5
        assert sqlite_replays(path) == 0

    def test_a_last_frame_cut_off_mid_write_is_no_loss(self, tmp_path: Path) -> None:
        path = crash_image(tmp_path, datagrams=5)
        wal = Path(f"{path}-wal")
        whole = scan_wal(wal, page_size=PAGE)
        with wal.open("r+b") as handle:  # the header of a next frame, and half its page
            handle.seek(32 + whole.frames * FRAME)
            handle.write(b"\x00" * (24 + PAGE // 2))
        assert scan_wal(wal, page_size=PAGE) == whole
        flip(wal, 32 + (whole.frames - 1) * FRAME + 24 + 7)  # the last whole frame's page
        scan = scan_wal(wal, page_size=PAGE)
        # Its transaction (several frames) had not committed when the writer died.
        assert scan.lost_frames == 0
        assert scan.uncommitted == whole.frames - scan.replayed > 1
        assert scan.replayed == sqlite_replays(path)

    def test_frames_left_from_an_earlier_generation_are_no_loss(self, tmp_path: Path) -> None:
        live = tmp_path / "live"
        live.mkdir()
        spool = Spool(live / "spool.db")
        write(spool, 0, 40)
        assert spool.checkpointer is not None
        spool.checkpointer.stop()  # no checkpoint of the worker's to race this one
        done = spool._db.execute("PRAGMA wal_checkpoint(RESTART)").fetchone()
        assert done[0] == 0  # the next write rewinds the log
        write(spool, 40, 3)
        shutil.copyfile(live / "spool.db-wal", tmp_path / "copy-wal")
        spool.close()
        scan = scan_wal(tmp_path / "copy-wal", page_size=PAGE)
        assert scan.frames > scan.replayed > 0
        assert (scan.lost_frames, scan.lost_commits, scan.uncommitted) == (0, 0, 0)

    def test_what_a_rolled_back_transaction_left_in_the_log_is_no_loss(
        self, tmp_path: Path
    ) -> None:
        db = sqlite3.connect(tmp_path / "live.db", isolation_level=None)
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("CREATE TABLE t (b BLOB)")
        db.execute("PRAGMA cache_size=10")  # the big transaction spills pages into the log
        db.execute("BEGIN")
        for _ in range(300):
            db.execute("INSERT INTO t VALUES (randomblob(1000))")
        db.execute("ROLLBACK")
        db.execute("INSERT INTO t VALUES (zeroblob(10))")  # overwrites the first of them
        for name in ("live.db", "live.db-wal"):
            shutil.copyfile(tmp_path / name, tmp_path / name.replace("live", "image"))
        db.close()
        scan = scan_wal(tmp_path / "image.db-wal", page_size=PAGE)
        assert scan.frames > scan.replayed + 20
        assert (scan.lost_frames, scan.lost_commits) == (0, 0)
        assert scan.uncommitted == scan.frames - scan.replayed
        assert sqlite_replays(tmp_path / "image.db") == scan.replayed


class TestStart:
    """What the gateway's spool does with what the check finds."""

    def test_a_clean_start_reports_ok_and_no_loss(self, tmp_path: Path) -> None:
        path = crash_image(tmp_path)
        spool = Spool(path)
        status = spool.start_check.status()
        spool.close()
        assert status["integrity"] == "ok"
        assert status["wal_lost_frames"] == status["wal_lost_commits"] == 0
        assert status["wal_replayed_frames"] == status["wal_frames"] > 0
        assert status["wal_copy"] is None
        assert list(path.parent.glob("*.corrupt-*")) == []

    def test_a_damaged_log_is_kept_beside_the_spool_and_said_loudly(self, tmp_path: Path) -> None:
        path = crash_image(tmp_path)
        wal = Path(f"{path}-wal")
        flip(wal, 32 + 20 * FRAME + 24 + 5)
        damaged = wal.read_bytes()
        with structlog.testing.capture_logs() as logs:
            spool = Spool(path)
        check = spool.start_check
        held_now = len(spool.pending("slb", limit=1000))
        # Replayed into the database and the log emptied: the rest is only in the copy.
        assert wal.stat().st_size < len(damaged) // 10
        write(spool, 100, 3)
        again = crash_image_of(spool, tmp_path / "again")
        spool.close()
        reopened = Spool(again)  # after a next crash: the frames are not counted twice
        reopened.close()
        assert reopened.start_check.wal is not None
        assert (reopened.start_check.lost_frames, reopened.start_check.lost_commits) == (0, 0)
        assert check.wal is not None
        assert check.lost_frames == check.wal.lost_frames > 0
        assert check.lost_commits > 0
        assert check.wal_copy is not None
        assert check.wal_copy.name.startswith("spool.db-wal.corrupt-")
        assert check.wal_copy.read_bytes() == damaged
        assert check.wal_copy.stat().st_mode & 0o777 == 0o600
        (lost,) = [e for e in logs if e["event"] == "spool_wal_frames_lost"]
        assert lost["log_level"] == "error"
        assert (lost["lost_frames"], lost["lost_commits"]) == (
            check.lost_frames,
            check.lost_commits,
        )
        assert lost["copy"] == str(check.wal_copy)
        assert held_now < 60
        assert check.status()["integrity"] == "ok"  # the database itself is sound

    def test_a_damaged_database_is_moved_aside_and_the_spool_starts_empty(
        self, tmp_path: Path
    ) -> None:
        path = tmp_path / "spool.db"
        spool = Spool(path)
        write(spool, 0, 200)
        spool.close()
        with path.open("r+b") as handle:  # a b-tree page of the events table, overwritten
            handle.seek(3 * PAGE)
            handle.write(b"\xa5" * PAGE)
        with structlog.testing.capture_logs() as logs:
            spool = Spool(path)
        check = spool.start_check
        assert check.integrity == "corrupt"
        assert check.problems
        assert check.moved_to is not None
        assert check.moved_to.exists()
        assert spool.pending_counts() == {}
        write(spool, 0, 1)  # the new spool takes events in
        assert spool.pending_counts() == {"slb": 1}
        spool.close()
        (moved,) = [e for e in logs if e["event"] == "spool_corrupt_moved_aside"]
        assert moved["log_level"] == "error"
        assert moved["moved_to"] == str(check.moved_to)

    def test_a_file_that_is_not_a_database_is_moved_aside(self, tmp_path: Path) -> None:
        path = tmp_path / "spool.db"
        path.write_bytes(b"not a database at all " * 500)
        spool = Spool(path)
        assert spool.start_check.integrity == "corrupt"
        assert spool.start_check.moved_to is not None
        assert spool.start_check.moved_to.read_bytes().startswith(b"not a database")
        spool.close()

    def test_the_integrity_check_is_cut_short_at_its_budget(self, tmp_path: Path) -> None:
        path = tmp_path / "spool.db"
        spool = Spool(path)
        write(spool, 0, 1000)  # enough pages for the check to take 10,000 steps
        spool.close()
        db = sqlite3.connect(path)
        try:
            assert check_integrity(db, budget_s=-1.0) == ("unchecked", [])
            assert check_integrity(db, budget_s=60.0) == ("ok", [])
        finally:
            db.close()

    def test_the_command_beside_the_gateway_checks_nothing(self, tmp_path: Path) -> None:
        path = crash_image(tmp_path)
        flip(Path(f"{path}-wal"), 32 + 20 * FRAME + 24 + 5)
        beside = Spool(path, exclusive=False)
        assert beside.start_check.integrity == "skipped"
        beside.close()
        assert list(path.parent.glob("*.corrupt-*")) == []


def take_until_refused(spool: Spool) -> int:
    """Datagrams of one large detection until a commit fails; how many the spool holds."""
    big = detection(1).model_copy(update={"subtype": "x" * 200})
    for n in range(1, 200):
        try:
            with spool.batch():
                spool.append(big.model_copy(update={"event_id": f"det-{n}"}), ("slb",))
                spool.remember(f"det-{n}")
        except SpoolError:
            return n
    raise AssertionError("every commit succeeded")


class TestFailedCommits:
    """A write that does not commit is counted by reason and said, and takes nothing in."""

    def test_a_full_database_fails_the_commit_counts_it_and_recovers(self, tmp_path: Path) -> None:
        spool = Spool(tmp_path / "spool.db")
        write(spool, 0, 1)
        pages = spool._db.execute("PRAGMA page_count").fetchone()[0]
        spool._db.execute(f"PRAGMA max_page_count={pages}")  # SQLITE_FULL on growth
        with structlog.testing.capture_logs() as logs:
            taken = take_until_refused(spool)
        assert spool.commits.failing
        assert spool.commits.failures == {"full": 1}
        assert "full" in spool.commits.reason
        last = spool.commits.status()["last_failure"]
        assert last["reason"] == "full"
        assert last["error"]
        (logged,) = [e for e in logs if e["event"] == "spool_commit_failed"]
        assert logged["log_level"] == "error"
        # Nothing of the failed datagram is held or remembered: it is taken again when re-sent.
        held_ids = [s.event.event_id for s in spool.pending("slb", limit=1000)]
        assert held_ids == [f"det-{n}" for n in range(taken)]
        assert not spool.seen(f"det-{taken}")
        spool._db.execute("PRAGMA max_page_count=1073741823")  # the disk is freed
        assert spool.probe()
        assert not spool.commits.failing
        assert spool.commits.reason == ""
        assert spool.commits.failures == {"full": 1}
        spool.close()
