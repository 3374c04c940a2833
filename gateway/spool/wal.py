"""SQLite's write-ahead log, read the way SQLite's recovery reads it, to count what it drops.

When a database in WAL mode is opened after a crash, SQLite rebuilds its index of the log
from the ``-wal`` file: it reads frames in order while each one carries the header's salts
and continues the checksum chain, and replays them up to the last *commit* frame (a frame
whose header gives the database size after the commit). Everything after the first frame
that fails is ignored without a word, and SQLite then overwrites it. A damaged byte in the
middle of the log therefore drops every transaction committed after it.

``scan_wal`` reads the file before SQLite opens it and says what SQLite will keep and what
it will drop. The format (https://www.sqlite.org/fileformat2.html#walformat): a 32-byte
header (magic, version, page size, checkpoint sequence, two salts, two checksums), then
frames of a 24-byte header (page number, database size for a commit frame or 0, the two
salts, two cumulative checksums) and one page. Header fields are big-endian; the checksums
sum 32-bit words in the byte order the magic number names.

Frames carrying other salts are left over from an earlier generation of the log (SQLite
rewinds the file after a checkpoint and changes the salts): they were copied into the
database already and are no loss. Past a frame of the current generation that fails, what
counts is whether a *commit* frame of the current generation follows: then committed
transactions are lost. Without one it is no loss: a last frame cut off by the crash (SQLite
writes a frame's header and its page separately) or the frames a rolled-back transaction
left behind, whose transactions never committed; they are counted as uncommitted.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

__all__ = ["WalScan", "db_page_size", "scan_wal"]

_HEADER = 32
_FRAME_HEADER = 24
_MAGIC_LE, _MAGIC_BE = 0x377F0682, 0x377F0683
_VERSION = 3007000
_MASK = 0xFFFFFFFF
_DEFAULT_PAGE = 4096


@dataclass(frozen=True, slots=True)
class WalScan:
    """What one ``-wal`` file holds, and what SQLite will replay of it."""

    #: Whole frames in the file (any generation).
    frames: int
    #: Frames SQLite replays: up to and with the last valid commit frame.
    replayed: int
    #: Committed transactions among them.
    commits: int
    #: Frames SQLite will not replay up to the last commit frame past a failing frame.
    lost_frames: int
    #: Commit frames among the lost ones: committed transactions that are gone.
    lost_commits: int
    #: Frames of the current generation past the last commit (replayed or lost): no loss.
    uncommitted: int
    #: Why frames are lost ("" when none are): which frame fails and how.
    problem: str

    @property
    def lost(self) -> bool:
        """True when SQLite will drop committed transactions."""
        return self.lost_commits > 0


def _checksum(data: bytes, s0: int, s1: int, *, big: bool) -> tuple[int, int]:
    """SQLite's WAL checksum of ``data`` (a multiple of 8 bytes), continuing from (s0, s1)."""
    words = struct.unpack(f"{'>' if big else '<'}{len(data) // 4}I", data)
    pairs = iter(words)
    for first, second in zip(pairs, pairs, strict=True):
        s0 = (s0 + first + s1) & _MASK
        s1 = (s1 + second + s0) & _MASK
    return s0, s1


def _page_size(value: int) -> int | None:
    return value if 512 <= value <= 65536 and value & (value - 1) == 0 else None


def db_page_size(database: Path) -> int | None:
    """The page size in a database file's header, None if it has none (new, or not SQLite)."""
    try:
        with database.open("rb") as handle:
            head = handle.read(18)
    except OSError:
        return None
    if len(head) < 18 or not head.startswith(b"SQLite format 3\x00"):
        return None
    raw = int.from_bytes(head[16:18], "big")
    return 65536 if raw == 1 else _page_size(raw)


def scan_wal(wal: Path, *, page_size: int | None = None) -> WalScan:
    """Read ``wal`` as SQLite's recovery would; ``page_size`` is the database's, if known.

    A header SQLite does not accept makes it ignore the whole file: every frame up to the
    last commit frame is then counted as lost (some may be from an earlier generation: an
    upper bound). Raises ``OSError`` if the file cannot be read.
    """
    with wal.open("rb") as handle:
        size = handle.seek(0, 2)
        handle.seek(0)
        header = handle.read(_HEADER)
        if len(header) < _HEADER:
            return WalScan(0, 0, 0, 0, 0, 0, "")
        magic, version, raw_page, _ckpt, salt1, salt2, c1, c2 = struct.unpack(">8I", header)
        big = magic == _MAGIC_BE
        page = _page_size(raw_page)
        header_ok = (
            magic in (_MAGIC_LE, _MAGIC_BE)
            and version == _VERSION
            and page is not None
            and (page_size is None or page == page_size)
            and _checksum(header[:24], 0, 0, big=big) == (c1, c2)
        )
        page = page_size or page or _DEFAULT_PAGE
        frame_bytes = _FRAME_HEADER + page
        frames = (size - _HEADER) // frame_bytes
        if not header_ok:
            commit_frames = []
            for index in range(1, frames + 1):
                handle.seek(_HEADER + (index - 1) * frame_bytes)
                if struct.unpack(">2I", handle.read(8))[1]:
                    commit_frames.append(index)
            if not commit_frames:
                return WalScan(frames, 0, 0, 0, 0, frames, "")
            last = commit_frames[-1]
            problem = "the header is damaged: SQLite ignores the whole file"
            return WalScan(frames, 0, 0, last, len(commit_frames), frames - last, problem)
        return _scan_frames(handle, frames, page, (salt1, salt2), (c1, c2), big=big)


def _scan_frames(
    handle: BinaryIO,
    frames: int,
    page: int,
    salts: tuple[int, int],
    chain: tuple[int, int],
    *,
    big: bool,
) -> WalScan:
    replayed = commits = 0
    first_bad = 0  # 1-based index of the first current frame that fails; 0: none
    problem = ""
    last_current = 0  # 1-based index of the last frame carrying the header's salts
    commit_frames: list[int] = []  # 1-based indexes of the commit frames carrying the salts
    for index in range(1, frames + 1):
        if first_bad:  # past the failure only headers are read: which frames are current
            handle.seek(_HEADER + (index - 1) * (_FRAME_HEADER + page))
            head = handle.read(_FRAME_HEADER)
            pgno, size_after, f1, f2 = struct.unpack(">4I", head[:16])
            if (f1, f2) == salts:
                last_current = index
                if size_after:
                    commit_frames.append(index)
            continue
        head = handle.read(_FRAME_HEADER)
        body = handle.read(page)
        pgno, size_after, f1, f2, k1, k2 = struct.unpack(">6I", head)
        if (f1, f2) != salts:
            first_bad, problem = index, f"frame {index} carries other salts"
            continue
        last_current = index
        if size_after:
            commit_frames.append(index)
        expected = _checksum(head[:8] + body, *chain, big=big)
        if pgno == 0 or expected != (k1, k2):
            first_bad, problem = index, f"frame {index} fails its checksum"
            continue
        chain = (k1, k2)
        if size_after:
            replayed = index
            commits += 1
    lost_commits = sum(1 for index in commit_frames if index > replayed)
    if not first_bad or first_bad >= last_current or not lost_commits:
        # No commit follows the failure: the end of this generation, the last frame cut off
        # mid-write, or what a rolled-back transaction left (SQLite writes pages to the log
        # before the commit when its cache is full; after a rollback a shorter transaction
        # overwrites only the start of them). None of it had committed.
        return WalScan(frames, replayed, commits, 0, 0, last_current - replayed, "")
    last_commit = commit_frames[-1]
    return WalScan(
        frames,
        replayed,
        commits,
        last_commit - replayed,
        lost_commits,
        last_current - last_commit,
        problem,
    )
