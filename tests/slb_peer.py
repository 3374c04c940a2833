"""An SLB server for tests: object item reports in, reconnaissance orders out, over HTTPS.

``SlbPeer`` is an ``https_peer.HttpsPeer`` (loopback, its own trustme CA, client
certificates required) serving SLB's side of ``docs/slb.md`` below ``/slb/api``:

- ``POST /object-items``: the body is checked with ``jsonschema`` against the shipped
  ``slb-object-item`` schema and its ``event_id`` against ``Idempotency-Key`` (400 naming the
  problem otherwise). Accepted documents are recorded by key (``accepted``); a key seen
  before is answered 409 and counted in ``duplicates``, never recorded twice. ``refuse`` maps
  keys to the status they get (422 ...). The first ``fail_first`` POSTs get 503 and the first
  ``busy_first`` get 429, both with ``Retry-After: <retry_after>`` when it is given;
- ``GET /orders?limit=N``: the queued orders (``queue_order``) that have no receipt yet, at
  most N, as ``{"orders": [...]}``; 204 when there are none. The orders are sent as queued,
  malformed ones included; ``orders_body`` (bytes), when set, is sent instead, verbatim.
  The first ``busy_polls`` GETs get 429 (with ``Retry-After`` when given);
- ``POST /orders/<order_id>/receipt``: checked against the schema's ``$defs/receipt``,
  recorded in ``receipts`` and the order is no longer offered; 404 for an order never queued.
  The first ``fail_receipts`` receipts get 503 instead.

``down = True`` closes every connection before the handshake (SLB unreachable).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any
from urllib.parse import unquote

from https_peer import Answer, Head, HttpsPeer
from jsonschema import Draft202012Validator

from sinks.slb.jc3iedm import load_schema
from sinks.slb.order import load_order_schema

__all__ = ["BASE", "SlbPeer"]

BASE = "/slb/api"
_ITEMS = f"{BASE}/object-items"
_ORDERS = f"{BASE}/orders"


def _validator(schema: dict[str, Any]) -> Draft202012Validator:
    return Draft202012Validator(schema, format_checker=Draft202012Validator.FORMAT_CHECKER)


def _first_problem(validator: Draft202012Validator, document: Any) -> str | None:
    problems = sorted(validator.iter_errors(document), key=lambda e: list(e.path))
    if not problems:
        return None
    where = "/".join(str(p) for p in problems[0].absolute_path)
    return f"schema: /{where}: {problems[0].message}"


class SlbPeer(HttpsPeer):
    """SLB's object item and order endpoints over real HTTPS with client certificates."""

    def __init__(
        self,
        directory: Path,
        *,
        fail_first: int = 0,
        busy_first: int = 0,
        retry_after: str | None = None,
        fail_receipts: int = 0,
        busy_polls: int = 0,
        drop_first: int = 0,
        refuse: Mapping[str, int] | None = None,
        server_name: str = "127.0.0.1",
    ) -> None:
        super().__init__(
            directory, drop_first=drop_first, server_name=server_name, file_prefix="slb"
        )
        self.fail_first = fail_first
        self.busy_first = busy_first
        self.retry_after = retry_after
        self.fail_receipts = fail_receipts
        self.busy_polls = busy_polls
        #: When set, the answer to every GET /orders, verbatim (hostile bodies).
        self.orders_body: bytes | None = None
        self.refuse = dict(refuse or {})
        #: Accepted documents by Idempotency-Key, in arrival order; a key at most once.
        self.accepted: dict[str, dict[str, Any]] = {}
        #: POSTs of a key already accepted (answered 409).
        self.duplicates = 0
        #: Orders offered until a receipt comes, by order id (or a stand-in key), in order.
        self.orders: dict[str, Any] = {}
        #: Receipts recorded, in arrival order.
        self.receipts: list[dict[str, Any]] = []
        self._items = _validator(load_schema())
        order_schema = load_order_schema()
        self._receipt = _validator({"$defs": order_schema["$defs"], "$ref": "#/$defs/receipt"})

    @property
    def base_url(self) -> str:
        """``https://127.0.0.1:PORT/slb/api``."""
        return f"https://127.0.0.1:{self.port}{BASE}"

    def sink_options(self, **extra: Any) -> dict[str, Any]:
        """Options of an ``slb`` sink that trusts this peer and is trusted by it."""
        return {"base_url": self.base_url, **self.tls_options(), **extra}

    def source_options(self, **extra: Any) -> dict[str, Any]:
        """Options of an ``slb`` source polling this peer (beside its name and type)."""
        return {"base_url": self.base_url, **self.tls_options(), **extra}

    def queue_order(self, order: Any) -> None:
        """Offer ``order`` (valid or not) from the next GET on, until it has a receipt."""
        key = order.get("order_id") if isinstance(order, dict) else None
        self.orders[str(key) if key is not None else f"(no id {len(self.orders)})"] = order

    def receipts_for(self, order_id: str) -> list[dict[str, Any]]:
        """The receipts recorded for ``order_id``."""
        return [r for r in self.receipts if r["order_id"] == order_id]

    def _retry_headers(self) -> dict[str, str]:
        return {} if self.retry_after is None else {"Retry-After": self.retry_after}

    def _answer(self, head: Head, body: bytes) -> Answer:
        if head.path == _ITEMS:
            if head.method != "POST":
                return 405, {"error": "object items are POSTed"}
            return self._item(head, body)
        if head.path == _ORDERS:
            if head.method != "GET":
                return 405, {"error": "orders are fetched with GET"}
            return self._offer(head)
        if head.path.startswith(_ORDERS + "/") and head.path.endswith("/receipt"):
            if head.method != "POST":
                return 405, {"error": "receipts are POSTed"}
            order_id = unquote(head.path[len(_ORDERS) + 1 : -len("/receipt")])
            return self._take_receipt(order_id, body)
        return 404, {"error": f"no such resource {head.path}"}

    def _item(self, head: Head, body: bytes) -> Answer:
        if self.fail_first > 0:
            self.fail_first -= 1
            return 503, {"error": "SLB busy"}, self._retry_headers()
        if self.busy_first > 0:
            self.busy_first -= 1
            return 429, {"error": "slow down"}, self._retry_headers()
        if head.headers.get("content-type", "").split(";")[0].strip() != "application/json":
            return 415, {"error": "expected application/json"}
        key = head.headers.get("idempotency-key", "")
        if not key:
            return 400, {"error": "Idempotency-Key is required"}
        try:
            document = json.loads(body)
        except ValueError as exc:
            return 400, {"error": f"not JSON: {exc}"}
        problem = _first_problem(self._items, document)
        if problem is not None:
            return 400, {"error": problem}
        if document["event_id"] != key:
            return 400, {"error": "Idempotency-Key differs from the document's event_id"}
        if key in self.refuse:
            return self.refuse[key], {"error": f"object item {key} refused by the test"}
        if key in self.accepted:
            self.duplicates += 1
            return 409, {"status": "duplicate", "event_id": key}
        self.accepted[key] = document
        return 201, {"status": "accepted", "event_id": key}

    def _offer(self, head: Head) -> Answer:
        if self.busy_polls > 0:
            self.busy_polls -= 1
            return 429, {"error": "slow down"}, self._retry_headers()
        if self.orders_body is not None:
            return 200, self.orders_body
        try:
            limit = int(head.query.get("limit", ["100"])[0])
        except ValueError:
            return 400, {"error": "limit must be a number"}
        if not self.orders:
            return 204, None
        return 200, {"orders": list(self.orders.values())[:limit]}

    def _take_receipt(self, order_id: str, body: bytes) -> Answer:
        if self.fail_receipts > 0:
            self.fail_receipts -= 1
            return 503, {"error": "SLB busy"}
        try:
            document = json.loads(body)
        except ValueError as exc:
            return 400, {"error": f"not JSON: {exc}"}
        problem = _first_problem(self._receipt, document)
        if problem is not None:
            return 400, {"error": problem}
        if document["order_id"] != order_id:
            return 400, {"error": "the receipt's order_id differs from the path's"}
        known = order_id in self.orders or any(r["order_id"] == order_id for r in self.receipts)
        if not known:
            return 404, {"error": f"no order {order_id}"}
        self.receipts.append(document)
        self.orders.pop(order_id, None)
        return 200, {"status": "recorded", "order_id": order_id}
