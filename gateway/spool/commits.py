"""Whether the spool's writes commit: failures by reason, the last one, and whether they fail now.

A write that does not commit (disk full, an I/O error, a read-only file system, another
process holding the write lock too long) takes nothing in: the datagram's detections are not
acknowledged and the airframes send them again. That is safe, and it must not be quiet:
each failure is counted by reason (``fg_spool_commit_failures_total``), the last one is on
/status, the gateway is not ready while the latest write failed, and the error is logged at
most once per ``_LOG_INTERVAL_S`` per reason.
"""

from __future__ import annotations

import sqlite3
from collections import Counter
from datetime import UTC, datetime
from typing import Any

import structlog

from gateway.ops.logsetup import RateLimit

__all__ = ["COMMIT_FAILURE_REASONS", "Commits", "failure_reason", "is_corruption"]

log = structlog.get_logger(__name__)

_LOG_INTERVAL_S = 10.0
# SQLite's primary result codes (the low byte of an extended code).
_BUSY, _LOCKED, _READONLY, _IOERR, _CORRUPT, _FULL, _CANTOPEN, _NOTADB = 5, 6, 8, 10, 11, 13, 14, 26
_REASONS = {
    _FULL: "full",
    _IOERR: "io",
    _CANTOPEN: "io",
    _READONLY: "readonly",
    _BUSY: "busy",
    _LOCKED: "busy",
    _CORRUPT: "corrupt",
    _NOTADB: "corrupt",
}
#: Every value ``failure_reason`` returns (the label values of the metric).
COMMIT_FAILURE_REASONS = ("full", "io", "readonly", "busy", "corrupt", "other")


def _code(exc: sqlite3.Error) -> int:
    return int(getattr(exc, "sqlite_errorcode", 0)) & 0xFF  # absent on errors of the module itself


def failure_reason(exc: sqlite3.Error) -> str:
    """A short reason for a failed write: full, io, readonly, busy, corrupt or other."""
    return _REASONS.get(_code(exc), "other")


def is_corruption(exc: sqlite3.Error) -> bool:
    """True if SQLite says the database file is damaged or is not a database at all."""
    return _code(exc) in (_CORRUPT, _NOTADB)


class Commits:
    """The record of one spool's writes that failed to commit."""

    def __init__(self, where: str) -> None:
        self.where = where
        self.failures: Counter[str] = Counter()
        #: Writes that committed, since start (a group commit counts once).
        self.committed = 0
        #: True while the latest write failed (cleared by the next one that commits).
        self.failing = False
        self._in_a_row = 0
        self._failing_at = ""
        self._last: dict[str, Any] | None = None
        self._log = RateLimit(interval_s=_LOG_INTERVAL_S)

    @property
    def total(self) -> int:
        """Writes that failed to commit, since start."""
        return sum(self.failures.values())

    def failed(self, exc: sqlite3.Error) -> None:
        """A write did not commit: count it, remember it, log it (rate-limited)."""
        reason = failure_reason(exc)
        self.failures[reason] += 1
        at = datetime.now(UTC).isoformat(timespec="seconds")
        if not self.failing:
            self._failing_at = at
        self._in_a_row += 1
        self.failing = True
        self._last = {"reason": reason, "error": str(exc)[:300], "at": at}
        if self._log.allow(reason):
            log.error(
                "spool_commit_failed",
                spool=self.where,
                reason=reason,
                error=str(exc)[:300],
                failures=self.failures[reason],
                note="nothing of this write is acknowledged: the airframes keep their "
                "detections and send them again; free the disk or fix the file system",
            )

    def succeeded(self) -> None:
        """A write committed: the spool takes events in again."""
        self.committed += 1
        if self.failing:
            self.failing = False
            log.warning(
                "spool_commits_recovered",
                spool=self.where,
                failed_in_a_row=self._in_a_row,
                failures=self.total,
            )
            self._in_a_row = 0

    @property
    def reason(self) -> str:
        """Why the spool takes nothing in now, "" while its writes commit."""
        if not self.failing or self._last is None:
            return ""
        return (
            f"writes fail to commit ({self._last['reason']}: {self._last['error']}), "
            f"{self._in_a_row} in a row since {self._failing_at}"
        )

    def status(self) -> dict[str, Any]:
        """For /status: whether writes fail now, the counts by reason, and the last failure."""
        return {
            "failing": self.failing,
            "failures": dict(self.failures),
            "last_failure": self._last,
        }
