"""The GUTE II sink: counter-UAS track handoffs to a battery, as JSON over HTTPS.

Each ``Handoff`` is POSTed to ``url`` as the document of ``gateway.codecs.gute`` with
``Idempotency-Key: <event_id>`` (the handoff id, with ``-r<n>`` for a revision), over TLS
with a client certificate and the battery's CA pinned (the hostname is always checked). A
handoff is a cue, never an order: the document always carries
``"operator_authorisation_required": true``, its schema allows nothing else, and nothing on
this path can command an effector; authorising an engagement stays with the battery's human
operator.

The sink holds no retry logic; its SinkRunner retries. The answer decides:

- 2xx: delivered; 409: the battery already has that key, so delivered too;
- 401, 403 (our certificate not accepted yet), 408, 425, 429, 5xx, a redirect (never
  followed), a timeout, a lost connection or a TLS failure: ``TransientSinkError`` naming the
  URL; the idempotency key makes the retry safe;
- any other 4xx: the rest of the batch is delivered first, then ``PermanentSinkError`` with
  ``event_ids`` names the refused handoffs and the server's reason (at most 512 bytes).

Logs carry handoff ids, statuses and counts, never a document, a key or a password.
"""

from __future__ import annotations

import ssl
from collections.abc import Sequence
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

import anyio
import anyio.to_thread
import httpx
import structlog
from pydantic import Field, ValidationInfo, field_validator, model_validator

from gateway.c2.sink import SinkConfig
from gateway.codecs.gute import encode_handoff
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import Event, EventKind, Handoff
from gateway.transports.https import (
    classify_answer,
    describe_https_error,
    https_client,
    read_at_most,
)
from gateway.transports.tls import TlsFiles, tls_problem, unreadable_file

__all__ = ["GuteSink", "GuteSinkConfig"]

log = structlog.get_logger(__name__)

#: How much of a refusal's body is read and quoted, at most.
MAX_REASON_BYTES = 512
_KINDS = frozenset({EventKind.HANDOFF})


class GuteSinkConfig(SinkConfig):
    """Options of the GUTE II sink: where the battery listens and the TLS material."""

    url: str = Field(description="https://HOST[:PORT]/PATH the handoffs are POSTed to.")
    ca_file: Path = Field(description="The only CA trusted for the battery's certificate.")
    cert_file: Path | None = Field(default=None, description="PEM client certificate (chain).")
    key_file: Path | None = Field(default=None, description="PEM key, if not in cert_file.")
    pkcs12_file: Path | None = Field(default=None, description="Client key and certificate.")
    password_file: Path | None = Field(
        default=None, description="File holding the key's or PKCS#12 password (never inline)."
    )
    timeout_s: float = Field(
        default=5.0, gt=0, le=300, description="Deadline of each phase: connect, write, read."
    )
    max_in_flight: int = Field(
        default=4, ge=1, le=32, description="Handoffs POSTed at once (and pooled connections)."
    )

    @field_validator("url")
    @classmethod
    def _https_only(cls, value: str) -> str:
        parts = urlsplit(value)
        try:
            port = parts.port
        except ValueError:
            port = -1
        if parts.scheme != "https" or not parts.hostname or port == -1:
            raise ValueError("expected https://HOST[:PORT]/PATH")
        if parts.username is not None or parts.password is not None:
            raise ValueError("no credentials in the URL; the client certificate identifies us")
        if parts.fragment:
            raise ValueError("a fragment is never sent: drop it")
        return value

    @model_validator(mode="after")
    def _one_client_certificate(self, info: ValidationInfo) -> GuteSinkConfig:
        if (self.cert_file is None) == (self.pkcs12_file is None):
            raise ValueError("give exactly one of cert_file (PEM) or pkcs12_file")
        if self.key_file is not None and self.cert_file is None:
            raise ValueError("key_file goes with cert_file")
        if self.password_file is not None and self.cert_file is None and self.pkcs12_file is None:
            raise ValueError("password_file goes with cert_file or pkcs12_file")
        if isinstance(info.context, dict) and info.context.get("environment"):
            # On the node (run, check-config): read the files now, so a missing CA or a wrong
            # password is a config error with its line, not a retry loop at the first cue.
            problem = tls_problem(self.tls_files)
            if problem is not None:
                raise ValueError(problem)
        return self

    @property
    def tls_files(self) -> TlsFiles:
        """The TLS material as the transports take it (paths only)."""
        return TlsFiles(
            self.ca_file, self.cert_file, self.key_file, self.pkcs12_file, self.password_file
        )


def _package_version() -> str:
    try:
        return version("fischer-gateway")
    except PackageNotFoundError:
        return "0"


@dataclass(frozen=True, slots=True)
class _Outcome:
    """What became of one POST."""

    event_id: str
    handoff_id: str
    result: Literal["delivered", "duplicate", "transient", "refused"]
    detail: str = ""


class GuteSink:
    """POSTs each handoff to one GUTE II battery; a cue for its operator, never an order."""

    config_model = GuteSinkConfig

    def __init__(self, name: str, config: GuteSinkConfig) -> None:
        self.name = name
        self.config = config
        self.url = config.url
        self._files = config.tls_files
        self._client: httpx.AsyncClient | None = None
        self._user_agent = f"fischer-gateway/{_package_version()}"
        self.log = log.bind(sink=name, url=config.url)

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Handoffs only."""
        return _KINDS

    def _fail(self, what: str) -> TransientSinkError:
        return TransientSinkError(f"sink {self.name}: {what}", sink=self.name)

    async def open(self) -> None:
        """Load the TLS material and make the client; connections open on the first POST.

        Raises ``TransientSinkError`` naming the file when the material cannot be loaded.
        """
        if self._client is not None:
            return
        timeout_s = self.config.timeout_s
        unreadable = await anyio.to_thread.run_sync(unreadable_file, self._files)
        if unreadable is not None:
            raise self._fail(f"{self.url}: {unreadable}")
        try:
            self._client = await https_client(
                self._files,
                connect_timeout_s=timeout_s,
                read_timeout_s=timeout_s,
                write_timeout_s=timeout_s,
                pool_timeout_s=timeout_s,
                max_connections=self.config.max_in_flight,
            )
        except OSError as exc:
            name = exc.filename or self._files.ca_file
            raise self._fail(f"{self.url}: {name}: {exc.strerror or exc}") from exc
        except (ssl.SSLError, ValueError) as exc:
            raise self._fail(f"{self.url}: TLS material unusable: {exc}") from exc

    async def send(self, batch: Sequence[Event]) -> None:
        """POST every handoff of ``batch`` (up to ``max_in_flight`` at once).

        Raises ``TransientSinkError`` if any POST should be retried (the whole batch is; the
        battery de-duplicates by key), else ``PermanentSinkError(event_ids=...)`` naming the
        handoffs refused for good, after every other one was delivered.
        """
        handoffs = [event for event in batch if isinstance(event, Handoff)]
        if not handoffs:
            return
        if self._client is None:
            await self.open()
        client = self._client
        assert client is not None  # noqa: S101 - open() made it or raised
        outcomes: list[_Outcome] = []
        limiter = anyio.CapacityLimiter(self.config.max_in_flight)

        async def post(handoff: Handoff) -> None:
            async with limiter:
                outcomes.append(await self._post(client, handoff))

        async with anyio.create_task_group() as tg:
            for handoff in handoffs:
                tg.start_soon(post, handoff)
        self._settle(outcomes, len(handoffs))

    def _settle(self, outcomes: list[_Outcome], total: int) -> None:
        delivered = sum(o.result in ("delivered", "duplicate") for o in outcomes)
        duplicates = sum(o.result == "duplicate" for o in outcomes)
        if delivered:
            self.log.info("gute_handoffs_delivered", count=delivered, duplicates=duplicates)
        transient = [o for o in outcomes if o.result == "transient"]
        if transient:
            first = transient[0]
            raise self._fail(
                f"{first.detail} ({len(transient)} of {total} handoffs to retry, "
                f"{delivered} delivered)"
            )
        refused = [o for o in outcomes if o.result == "refused"]
        if refused:
            for outcome in refused:
                self.log.warning(
                    "gute_handoff_refused", handoff_id=outcome.handoff_id, reason=outcome.detail
                )
            raise PermanentSinkError(
                f"sink {self.name}: {self.url} refused {len(refused)} of {total} handoffs: "
                + "; ".join(f"{o.handoff_id}: {o.detail}" for o in refused),
                sink=self.name,
                event_ids=[o.event_id for o in refused],
            )

    async def _post(self, client: httpx.AsyncClient, handoff: Handoff) -> _Outcome:
        key = handoff.event_id
        try:
            body = encode_handoff(handoff)
        except ValueError as exc:
            return _Outcome(handoff.event_id, key, "refused", str(exc))
        headers = {
            "Content-Type": "application/json",
            "Accept": "application/json",
            "Idempotency-Key": key,
            "User-Agent": self._user_agent,
        }
        try:
            async with client.stream("POST", self.url, content=body, headers=headers) as response:
                status = response.status_code
                reason = await read_at_most(response, MAX_REASON_BYTES)
        except (httpx.HTTPError, ssl.SSLError, OSError) as exc:
            detail = describe_https_error(exc, self.url, self._files)
            return _Outcome(handoff.event_id, key, "transient", detail)
        text = reason.decode("utf-8", "replace").strip() or response.reason_phrase
        # The status table shared with the slb sink. Retry-After is not read here (this sink's
        # behaviour is unchanged): the runner's backoff paces the retry of a cue.
        answer = classify_answer(self.url, status, response.headers, text, max_retry_after_s=0.0)
        result: Literal["delivered", "duplicate", "transient", "refused"] = (
            "transient" if answer.outcome == "retry" else answer.outcome
        )
        return _Outcome(handoff.event_id, key, result, answer.detail)

    async def aclose(self) -> None:
        """Close the pooled connections; safe before ``open`` and after a failed one."""
        client, self._client = self._client, None
        if client is not None:
            with anyio.move_on_after(self.config.timeout_s, shield=True):
                await client.aclose()
