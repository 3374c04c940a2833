"""One pooled HTTPS client that POSTs events one by one: what the ``gute2`` and ``slb`` sinks share.

``HttpsPoster`` loads the TLS material (``open``), POSTs each event's document with
``Idempotency-Key: <event_id>``, up to ``max_in_flight`` at once over kept TLS connections
(``gateway.transports.http1``: the pinned CA, the hostname checked, the client certificate
presented), each under one deadline for the whole exchange (connecting, sending, a server
trickling its answer), and keeps at most ``MAX_REASON_BYTES`` of the answer's body. A POST
that a kept connection lost before any answer is sent once more on a new connection: the
idempotency key makes the server take a second copy as a duplicate (409), never twice.
Every answer is classified by the table all HTTPS sinks share
(``gateway.transports.https.classify_answer``); what to do with the outcomes (log, hold back,
raise) stays with the sink.
"""

from __future__ import annotations

import asyncio
import ssl
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from typing import Literal, TypeVar

import anyio
import anyio.to_thread

from gateway.errors import HttpAnswerError, TransientSinkError
from gateway.events import Event
from gateway.transports.http1 import Http1Origin
from gateway.transports.https import classify_answer, describe_https_error
from gateway.transports.tls import TlsFiles, tls_context, unreadable_file

__all__ = ["MAX_REASON_BYTES", "HttpsPoster", "PostOutcome"]

#: How much of a refusal's body is read and quoted, at most.
MAX_REASON_BYTES = 512

E = TypeVar("E", bound=Event)


def _package_version() -> str:
    try:
        return version("fischer-gateway")
    except PackageNotFoundError:
        return "0"


@dataclass(frozen=True, slots=True)
class PostOutcome:
    """What became of one POST: delivered, a duplicate (409), to retry, or refused for good."""

    event_id: str
    result: Literal["delivered", "duplicate", "retry", "refused"]
    detail: str = ""
    retry_after_s: float | None = None


class HttpsPoster:
    """POSTs documents to one URL for the sink ``sink`` over kept connections."""

    def __init__(
        self,
        sink: str,
        url: str,
        files: TlsFiles,
        *,
        timeout_s: float,
        max_in_flight: int,
        max_retry_after_s: float = 0.0,
    ) -> None:
        self.sink = sink
        self.url = url
        self.files = files
        self.timeout_s = timeout_s
        self.max_in_flight = max_in_flight
        self.max_retry_after_s = max_retry_after_s
        self._client: Http1Origin | None = None
        self._user_agent = f"fischer-gateway/{_package_version()}"

    def fail(self, what: str) -> TransientSinkError:
        """A ``TransientSinkError`` of this sink saying ``what``."""
        return TransientSinkError(f"sink {self.sink}: {what}", sink=self.sink)

    async def open(self) -> None:
        """Load the TLS material and make the client; connections open on the first POST.

        Raises ``TransientSinkError`` naming the file when the material cannot be loaded.
        """
        if self._client is not None:
            return
        unreadable = await anyio.to_thread.run_sync(unreadable_file, self.files)
        if unreadable is not None:
            raise self.fail(f"{self.url}: {unreadable}")
        try:
            context = await anyio.to_thread.run_sync(tls_context, self.files)
            self._client = Http1Origin(self.url, context, max_connections=self.max_in_flight)
        except OSError as exc:
            name = exc.filename or self.files.ca_file
            raise self.fail(f"{self.url}: {name}: {exc.strerror or exc}") from exc
        except (ssl.SSLError, ValueError) as exc:
            raise self.fail(f"{self.url}: TLS material unusable: {exc}") from exc

    async def post_all(
        self, events: Sequence[E], encode: Callable[[E], bytes]
    ) -> list[PostOutcome]:
        """POST each of ``events`` as ``encode(event)``, up to ``max_in_flight`` at once.

        An event ``encode`` refuses (``ValueError``) is refused without a request. Opens the
        client first if need be (``TransientSinkError`` when it cannot).
        """
        await self.open()
        client = self._client
        assert client is not None  # noqa: S101 - open() made it or raised
        outcomes: list[PostOutcome] = []
        if len(events) == 1:
            # A lone cue (the usual batch) is POSTed from here: no task group, no limiter.
            event = events[0]
            try:
                body = encode(event)
            except ValueError as exc:
                return [PostOutcome(event.event_id, "refused", str(exc))]
            return [await self._post(client, event.event_id, body)]
        limiter = anyio.CapacityLimiter(self.max_in_flight)

        async def post(event: E) -> None:
            try:
                body = encode(event)
            except ValueError as exc:
                outcomes.append(PostOutcome(event.event_id, "refused", str(exc)))
                return
            async with limiter:
                outcomes.append(await self._post(client, event.event_id, body))

        async with anyio.create_task_group() as tg:
            for event in events:
                tg.start_soon(post, event)
        return outcomes

    async def _post(self, client: Http1Origin, key: str, body: bytes) -> PostOutcome:
        headers = {
            "Content-Type": "application/json",
            "Accept": "application/json",
            "Idempotency-Key": key,
            "User-Agent": self._user_agent,
        }
        try:
            # The loop's own deadline (one timer, no cancel scope), as the SinkRunner's.
            async with asyncio.timeout(self.timeout_s):
                reply = await client.post(headers, body, limit=MAX_REASON_BYTES)
        except TimeoutError:
            return PostOutcome(key, "retry", f"{self.url}: no answer within {self.timeout_s} s")
        except (HttpAnswerError, OSError) as exc:  # ssl.SSLError is an OSError
            return PostOutcome(key, "retry", describe_https_error(exc, self.url, self.files))
        except ValueError as exc:  # a key no HTTP header can carry: never sendable
            return PostOutcome(key, "refused", str(exc))
        text = reply.body.decode("utf-8", "replace").strip() or reply.reason_phrase
        answer = classify_answer(
            self.url, reply.status, reply.headers, text, max_retry_after_s=self.max_retry_after_s
        )
        return PostOutcome(key, answer.outcome, answer.detail, answer.retry_after_s)

    async def aclose(self) -> None:
        """Close the kept connections; safe before ``open`` and after a failed one."""
        client, self._client = self._client, None
        if client is not None:
            await client.aclose(self.timeout_s)
