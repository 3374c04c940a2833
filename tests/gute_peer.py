"""A GUTE II battery for tests: a real HTTPS server on loopback that takes handoffs.

``GutePeer`` is an ``https_peer.HttpsPeer`` (loopback, its own trustme CA, client
certificates required, enough HTTP/1.1 for a client) that validates every body with
``jsonschema`` against the shipped schema (400 when it fails), and records accepted
handoffs by ``Idempotency-Key``: a repeated key answers ``duplicate_status`` and is not
recorded twice. It can fail the first ``fail_first`` POSTs with 503, drop the
connection for the first ``drop_first`` POSTs, and refuse chosen keys with a chosen status.

In an async test::

    async with GutePeer(tmp_path) as peer:
        sink = GuteSink("gute", GuteSinkConfig(**peer.sink_options()))

From a sync test (a daemon subprocess, ``check_sink``), the server runs in a thread::

    with GutePeer(tmp_path).in_thread() as peer:
        write the daemon config with sinks: [{type: gute2, options: peer.sink_options()}]
        wait_until(lambda: len(peer.accepted) == 1, 10, "the handoff")

The CA, the client certificate and its key are PEM files in ``directory`` from construction
on (``peer.ca_file``, ``peer.cert_file``, ``peer.key_file``); ``peer.url`` is known once the
server listens.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from https_peer import Answer, Head, HttpsPeer, Request
from jsonschema import Draft202012Validator

from sinks.gute2.codec import SCHEMA_ID, SCHEMA_VERSIONS, load_schema

__all__ = ["PATH", "GutePeer", "Request"]

PATH = "/gute2/handoffs"


class GutePeer(HttpsPeer):
    """A GUTE II battery's handoff endpoint over real HTTPS with client certificates."""

    def __init__(
        self,
        directory: Path,
        *,
        fail_first: int = 0,
        drop_first: int = 0,
        refuse: Mapping[str, int] | None = None,
        duplicate_status: int = 409,
        server_name: str = "127.0.0.1",
    ) -> None:
        super().__init__(
            directory, drop_first=drop_first, server_name=server_name, file_prefix="gute"
        )
        self.fail_first = fail_first
        self.refuse = dict(refuse or {})
        self.duplicate_status = duplicate_status
        #: Accepted documents by Idempotency-Key, in arrival order; a key at most once.
        self.accepted: dict[str, dict[str, Any]] = {}
        #: One validator per schema version: a /1 document is still read by its own schema.
        self._validators = {
            version: Draft202012Validator(
                load_schema(version), format_checker=Draft202012Validator.FORMAT_CHECKER
            )
            for version in SCHEMA_VERSIONS
        }

    @property
    def url(self) -> str:
        """Where handoffs go: ``https://127.0.0.1:PORT/gute2/handoffs``."""
        return f"https://127.0.0.1:{self.port}{PATH}"

    def sink_options(self, **extra: Any) -> dict[str, Any]:
        """Options of a ``gute2`` sink that trusts this peer and is trusted by it."""
        return {"url": self.url, **self.tls_options(), **extra}

    def _answer(self, head: Head, body: bytes) -> Answer:
        if head.path != PATH:
            return 404, {"error": f"no such resource {head.path}"}
        if head.method != "POST":
            return 405, {"error": "handoffs are POSTed"}
        if self.fail_first > 0:
            self.fail_first -= 1
            return 503, {"error": "battery busy"}
        if head.headers.get("content-type", "").split(";")[0].strip() != "application/json":
            return 415, {"error": "expected application/json"}
        key = head.headers.get("idempotency-key", "")
        if not key:
            return 400, {"error": "Idempotency-Key is required"}
        try:
            document = json.loads(body)
        except ValueError as exc:
            return 400, {"error": f"not JSON: {exc}"}
        named = document.get("schema") if isinstance(document, dict) else None
        validator = self._validators.get(named if isinstance(named, str) else "")
        validator = validator or self._validators[SCHEMA_ID]
        problems = sorted(validator.iter_errors(document), key=lambda e: list(e.path))
        if problems:
            where = "/".join(str(p) for p in problems[0].absolute_path)
            return 400, {"error": f"schema: /{where}: {problems[0].message}"}
        if document["idempotency_key"] != key:
            return 400, {"error": "Idempotency-Key differs from the document's idempotency_key"}
        if key in self.refuse:
            return self.refuse[key], {"error": f"handoff {key} refused by the test"}
        if key in self.accepted:
            return self.duplicate_status, {"status": "duplicate", "handoff_id": key}
        self.accepted[key] = document
        return 201, {"status": "accepted", "handoff_id": key}
