"""The spool's order book: the orders processor's orders and statuses, durable across kill -9.

Implements ``gateway.domain.orderbook.OrderBook`` in two tables of the spool's database,
versioned on their own (``meta`` key ``orders_schema``):

- ``orders``: one row per order event id: the order (JSON), its content digest, where it
  stands (``waiting``, ``uploading``, ``executing``, ``done``), the airframe, the mission
  items planned (JSON), the waiting deadline, the last item reached, the newest status's
  sequence number and when the row was written;
- ``order_statuses``: every status published for an order, by sequence number, for the
  issuer (sent again after a restart) and ``fischer-gateway order --status ID``.

Writes join the spool's open group commit (``Spool.writing``): a row written as a status is
published commits with the status events the bus appends, or neither does. A group holding
a record never lingers past its loop pass: it commits at the end of the pass in which the
status was published, before any source's task runs to send it (a commit that fails is
logged and counted in ``failed``). At most
``max_orders`` orders are kept: beyond it the oldest done ones go, with their statuses.
"""

from __future__ import annotations

import json
import sqlite3
import time
from datetime import datetime
from typing import Any

import structlog
from pydantic import ValidationError

from gateway.domain.mission import Loiter, MissionStep, Waypoint
from gateway.domain.orderbook import OrderRecord, Phase
from gateway.errors import SpoolError
from gateway.events import FiveLineOrder, OrderStatus
from gateway.ops.logsetup import RateLimit
from gateway.spool.store import Spool

__all__ = ["SpoolOrderBook"]

log = structlog.get_logger(__name__)

_SCHEMA_VERSION = "1"
_SCHEMA = (
    """CREATE TABLE IF NOT EXISTS orders (
    event_id TEXT PRIMARY KEY,
    order_id TEXT NOT NULL,
    source TEXT NOT NULL,
    body TEXT NOT NULL,
    digest TEXT NOT NULL,
    phase TEXT NOT NULL,
    airframe TEXT,
    items TEXT NOT NULL,
    deadline TEXT,
    reached INTEGER NOT NULL,
    seq INTEGER NOT NULL,
    updated_at REAL NOT NULL
) WITHOUT ROWID""",
    "CREATE INDEX IF NOT EXISTS orders_order_id ON orders (source, order_id)",
    "CREATE INDEX IF NOT EXISTS orders_updated ON orders (phase, updated_at)",
    """CREATE TABLE IF NOT EXISTS order_statuses (
    event_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    body TEXT NOT NULL,
    PRIMARY KEY (event_id, seq)
) WITHOUT ROWID""",
)
_PHASES: frozenset[str] = frozenset({"waiting", "uploading", "executing", "done"})
_PRUNE_EVERY = 256


def _steps_json(items: tuple[MissionStep, ...]) -> str:
    rows: list[dict[str, Any]] = []
    for step in items:
        row: dict[str, Any] = {
            "lat_deg": step.lat_deg,
            "lon_deg": step.lon_deg,
            "alt_msl_m": step.alt_msl_m,
        }
        if isinstance(step, Loiter):
            row |= {"seconds": step.seconds, "radius_m": step.radius_m}
        rows.append(row)
    return json.dumps(rows)


def _steps(text: str) -> tuple[MissionStep, ...]:
    steps: list[MissionStep] = []
    for row in json.loads(text):
        point = (float(row["lat_deg"]), float(row["lon_deg"]), float(row["alt_msl_m"]))
        if "seconds" in row:
            steps.append(Loiter(*point, float(row["seconds"]), float(row["radius_m"])))
        else:
            steps.append(Waypoint(*point))
    return tuple(steps)


class SpoolOrderBook:
    """The order book in ``spool``'s database (see the module docstring)."""

    def __init__(self, spool: Spool, *, max_orders: int = 10_000) -> None:
        self._spool = spool
        self.max_orders = max_orders
        self._saves = 0
        #: Writes whose group commit failed (rolled back).
        self.failed = 0
        self._failed_log = RateLimit(interval_s=10.0)
        try:
            with spool.writing() as db:
                for statement in _SCHEMA:
                    db.execute(statement)
                row = db.execute("SELECT value FROM meta WHERE key='orders_schema'").fetchone()
                if row is None:
                    db.execute("INSERT INTO meta VALUES ('orders_schema', ?)", (_SCHEMA_VERSION,))
                elif row[0] != _SCHEMA_VERSION:
                    raise SpoolError(
                        f"{spool.path}: order book schema {row[0]}, this gateway reads"
                        f" {_SCHEMA_VERSION}"
                    )
        except sqlite3.Error as exc:
            raise SpoolError(f"{spool.path}: order book: {exc}") from exc
        spool.flush()

    def save(self, record: OrderRecord, status: OrderStatus | None = None) -> None:
        """Write ``record`` and ``status`` in the spool's open group commit."""
        order = record.order
        deadline = None if record.deadline is None else record.deadline.isoformat()
        try:
            with self._spool.writing() as db:
                db.execute(
                    "INSERT OR REPLACE INTO orders VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
                    (
                        order.event_id,
                        order.order_id,
                        order.source,
                        order.model_dump_json(),
                        record.digest,
                        record.phase,
                        record.airframe,
                        _steps_json(record.items),
                        deadline,
                        record.reached,
                        record.seq,
                        time.time(),
                    ),
                )
                if status is not None and status.seq is not None:
                    db.execute(
                        "INSERT OR REPLACE INTO order_statuses VALUES (?,?,?)",
                        (order.event_id, status.seq, status.model_dump_json()),
                    )
        except sqlite3.Error as exc:
            raise SpoolError(f"order book: {exc}") from exc
        group = self._spool.open_group
        if group is not None:
            group.when_done(self._committed)  # and so no linger: this pass's end commits it
        self._saves += 1
        if self._saves % _PRUNE_EVERY == 0:
            self.prune()

    def _committed(self, committed: bool) -> None:
        if not committed:
            self.failed += 1
            if self._failed_log.allow("failed"):
                log.error("order_book_commit_failed", failed=self.failed)

    def prune(self) -> int:
        """Forget the oldest done orders beyond ``max_orders``; how many went."""
        rows = self._spool.read("SELECT count(*) FROM orders")
        extra = int(str(rows[0][0])) - self.max_orders
        if extra <= 0:
            return 0
        try:
            with self._spool.writing() as db:
                gone = [
                    str(row[0])
                    for row in db.execute(
                        "SELECT event_id FROM orders WHERE phase='done' ORDER BY updated_at"
                        " LIMIT ?",
                        (extra,),
                    ).fetchall()
                ]
                db.executemany("DELETE FROM orders WHERE event_id=?", [(e,) for e in gone])
                db.executemany("DELETE FROM order_statuses WHERE event_id=?", [(e,) for e in gone])
        except sqlite3.Error as exc:
            raise SpoolError(f"order book: {exc}") from exc
        return len(gone)

    def load(self) -> list[OrderRecord]:
        """Every order kept, oldest first; a row that does not read back is skipped."""
        records = []
        for row in self._spool.read(
            "SELECT body, digest, phase, airframe, items, deadline, reached, seq, updated_at"
            " FROM orders ORDER BY updated_at"
        ):
            body, digest, phase, airframe, items, deadline, reached, seq, updated = row
            try:
                order = FiveLineOrder.model_validate_json(str(body))
                if phase not in _PHASES:
                    continue
                kept: Phase = phase  # type: ignore[assignment]
                records.append(
                    OrderRecord(
                        order=order,
                        digest=str(digest),
                        phase=kept,
                        airframe=None if airframe is None else str(airframe),
                        items=_steps(str(items)),
                        deadline=None
                        if deadline is None
                        else datetime.fromisoformat(str(deadline)),
                        reached=int(str(reached)),
                        seq=int(str(seq)),
                        updated=float(str(updated)),
                    )
                )
            except (ValidationError, ValueError, KeyError, TypeError):
                continue
        return records

    def statuses(self, order_event_id: str) -> list[OrderStatus]:
        """The statuses published for one order, by ``seq``."""
        return [
            OrderStatus.model_validate_json(str(row[0]))
            for row in self._spool.read(
                "SELECT body FROM order_statuses WHERE event_id=? ORDER BY seq",
                (order_event_id,),
            )
        ]

    def find(self, order_id: str, source: str | None = None) -> list[str]:
        """The order event ids kept for an issuer's ``order_id`` (of ``source`` if given)."""
        if source is None:
            rows = self._spool.read("SELECT event_id FROM orders WHERE order_id=?", (order_id,))
        else:
            rows = self._spool.read(
                "SELECT event_id FROM orders WHERE source=? AND order_id=?", (source, order_id)
            )
        return [str(row[0]) for row in rows]
