"""HTTPS to one C2 destination: the pinned CA, a client certificate, bounded everything.

``https_client`` builds an ``httpx.AsyncClient`` whose TLS context is ``tls_context``'s (only
the configured CA is trusted, the hostname is always checked, the client certificate is
presented). It ignores the environment (no proxy variables, no ``SSL_CERT_FILE``, no netrc),
never follows a redirect, keeps a small connection pool and has a deadline for each phase.
``read_at_most`` reads a response body up to a bound, never more, and
``describe_https_error`` turns what httpx or OpenSSL raised into one sentence naming the URL
and, for TLS, the CA file, the hostname or the client certificate.

``classify_answer`` is the one table by which every HTTPS sink (GUTE II, SLB) takes a
server's status code: delivered, already delivered (409), worth retrying (with the server's
``Retry-After``, bounded) or refused for good.
"""

from __future__ import annotations

import importlib
import socket
import ssl
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime
from email.utils import parsedate_to_datetime
from typing import Literal
from urllib.parse import urlsplit

import anyio.to_thread
import httpx

from gateway.clock import utc_now
from gateway.errors import HttpAnswerError, os_reason
from gateway.transports.tls import TlsFiles, describe_tls_error, tls_context

__all__ = [
    "RETRY_STATUSES",
    "Answer",
    "classify_answer",
    "describe_https_error",
    "https_client",
    "read_at_most",
    "retry_after_s",
]

#: Statuses retried besides 5xx. 401/403: the server does not (yet) accept our certificate,
#: which an operator fixes (a renewed or newly enrolled certificate), so the events are kept
#: and retried, never dead-lettered. 408, 425, 429: the server asks us to come back.
RETRY_STATUSES = frozenset({401, 403, 408, 425, 429})
#: Statuses whose ``Retry-After`` is honoured (RFC 9110: a 503's or a 429's wait).
_RETRY_AFTER_STATUSES = frozenset({429, 503})
#: A ``Retry-After`` longer than this is not a number of seconds or a date we read.
_MAX_RETRY_AFTER_CHARS = 64

# OpenSSL alert reasons a server sends when it refuses the client's certificate.
_CLIENT_CERT_REFUSED = (
    "CERTIFICATE_REQUIRED",
    "BAD_CERTIFICATE",
    "UNKNOWN_CA",
    "CERTIFICATE_UNKNOWN",
    "UNSUPPORTED_CERTIFICATE",
    "ACCESS_DENIED",
)


async def https_client(
    files: TlsFiles,
    *,
    connect_timeout_s: float,
    read_timeout_s: float,
    write_timeout_s: float,
    pool_timeout_s: float,
    max_connections: int = 4,
) -> httpx.AsyncClient:
    """A client for one HTTPS destination, its TLS material read in a worker thread.

    Raises ``OSError`` for a missing or unreadable file and ``ssl.SSLError`` or ``ValueError``
    for unusable contents (``tls_context``); the messages name the file, never a password.
    """
    context = await anyio.to_thread.run_sync(tls_context, files)
    # httpcore imports its network backend on the first request, on the event loop; import it
    # here, off the loop, so a first POST on a busy node does not hold the loop for it.
    await anyio.to_thread.run_sync(importlib.import_module, "httpcore._backends.anyio")
    return httpx.AsyncClient(
        verify=context,
        trust_env=False,
        follow_redirects=False,
        timeout=httpx.Timeout(
            connect=connect_timeout_s,
            read=read_timeout_s,
            write=write_timeout_s,
            pool=pool_timeout_s,
        ),
        limits=httpx.Limits(
            max_connections=max_connections,
            max_keepalive_connections=max_connections,
            keepalive_expiry=30.0,
        ),
    )


async def read_at_most(response: httpx.Response, limit: int) -> bytes:
    """At most ``limit`` bytes of a streamed ``response``'s body; the rest is never read.

    The caller closes the response (``async with client.stream(...)``), which drops the
    connection if the body was cut short.
    """
    body = bytearray()
    async for chunk in response.aiter_raw():
        body += chunk[: limit - len(body)]
        if len(body) >= limit:
            break
    return bytes(body)


def _ssl_cause(exc: BaseException) -> ssl.SSLError | None:
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, ssl.SSLError):
            return seen
        seen = seen.__cause__ or seen.__context__
    return None


def _client_certificate(files: TlsFiles) -> str | None:
    path = files.cert_file or files.pkcs12_file
    return None if path is None else str(path)


def describe_https_error(exc: BaseException, url: str, files: TlsFiles) -> str:
    """One sentence for a failed request to ``url``: what failed and, for TLS, whose fault.

    Names the pinned CA file when the server's certificate is not trusted, the hostname when
    the certificate is for another name, and the client certificate when the server refused
    it. Never includes a password or a request body.
    """
    hostname = urlsplit(url).hostname or url
    tls = _ssl_cause(exc)
    if tls is not None:
        reason = str(tls.reason or "")
        if not isinstance(tls, ssl.SSLCertVerificationError) and any(
            alert in reason for alert in _CLIENT_CERT_REFUSED
        ):
            mine = _client_certificate(files)
            if mine is None:
                return f"{url}: the server requires a client certificate and none is configured"
            return f"{url}: the server refused the client certificate {mine} ({reason})"
        return f"{url}: {describe_tls_error(tls, files, hostname)}"
    if isinstance(exc, httpx.TimeoutException):
        phase = {
            httpx.ConnectTimeout: "connecting",
            httpx.ReadTimeout: "waiting for the answer",
            httpx.WriteTimeout: "sending the request",
            httpx.PoolTimeout: "waiting for a free connection",
        }.get(type(exc), "on the request")
        return f"{url}: timed out {phase}"
    text = str(exc) or type(exc).__name__
    if isinstance(exc, httpx.ConnectError | ConnectionRefusedError | socket.gaierror):
        return f"{url}: cannot connect: {text}"
    if isinstance(exc, httpx.RemoteProtocolError | httpx.ReadError | httpx.WriteError):
        return f"{url}: connection lost: {text}"
    if isinstance(exc, ConnectionError):  # reset, aborted, broken pipe
        return f"{url}: connection lost: {text}"
    if isinstance(exc, HttpAnswerError):
        return f"{url}: unreadable answer: {text}"
    if isinstance(exc, OSError):
        return f"{url}: network error: {os_reason(exc)}"
    return f"{url}: {type(exc).__name__}: {text}"


@dataclass(frozen=True, slots=True)
class Answer:
    """How one HTTP answer of a C2 server is to be taken.

    ``outcome``: ``delivered`` (2xx), ``duplicate`` (409: the server already has the
    idempotency key, so delivered too), ``retry`` (try again later; ``retry_after_s`` is the
    server's bounded wait, or None) or ``refused`` (never accepted). ``detail`` is one
    sentence naming the URL and the status, for the error and the log.
    """

    outcome: Literal["delivered", "duplicate", "retry", "refused"]
    detail: str = ""
    retry_after_s: float | None = None


def retry_after_s(
    value: str | None, *, limit_s: float, clock: Callable[[], datetime] = utc_now
) -> float | None:
    """Seconds to wait from a ``Retry-After`` header: delta-seconds or an HTTP date.

    At most ``limit_s`` (a server cannot park us for a day), at least 0; None when the header
    is absent or unreadable, which is never an error.
    """
    if value is None:
        return None
    text = value.strip()
    if not text or len(text) > _MAX_RETRY_AFTER_CHARS:
        return None
    if text.isascii() and text.isdigit():  # str.isdigit alone takes '²', float does not
        seconds = float(text)
    else:
        try:
            when = parsedate_to_datetime(text)
        except (TypeError, ValueError, IndexError, OverflowError):
            return None
        if when.tzinfo is None:
            return None  # RFC 9110 dates are GMT; a date without a zone is not one
        seconds = (when - clock()).total_seconds()
    return min(max(seconds, 0.0), limit_s)


def classify_answer(
    url: str,
    status: int,
    headers: Mapping[str, str],
    text: str,
    *,
    max_retry_after_s: float,
    clock: Callable[[], datetime] = utc_now,
) -> Answer:
    """Take ``status`` from ``url`` by the one table every HTTPS sink uses.

    2xx: delivered; 409: duplicate (delivered before); 5xx, ``RETRY_STATUSES`` and a redirect
    (never followed: the configured URL is wrong): retry, with ``Retry-After`` read for 429
    and 503 (bounded by ``max_retry_after_s``); any other 4xx: refused. ``text`` is the
    server's reason (already bounded by the caller); ``headers`` are looked up in lower case.
    """
    if 200 <= status < 300:
        return Answer("delivered")
    if status == 409:
        return Answer("duplicate")
    if 300 <= status < 400:
        where = headers.get("location", "?")
        return Answer(
            "retry", f"{url}: HTTP {status} redirect to {where!r} not followed; fix the url"
        )
    if status in RETRY_STATUSES or status >= 500:
        wait = None
        if status in _RETRY_AFTER_STATUSES:
            wait = retry_after_s(headers.get("retry-after"), limit_s=max_retry_after_s, clock=clock)
        return Answer("retry", f"{url}: HTTP {status}: {text}", wait)
    return Answer("refused", f"HTTP {status}: {text}")
