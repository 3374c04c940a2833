"""One connection to a SWECCIS server: TLS with our certificate, frames, registration, acks.

Shared by the ``sweccis`` sink and the ``sweccis`` order source; docs/sweccis.md describes
the protocol. ``SweccisLink.connect`` opens TLS 1.2+ to ``tls://HOST:PORT`` (the CA pinned,
the hostname checked, our client certificate presented), sends ``Register`` with the FAS the
connection publishes and those it subscribes to, and returns once the server's
``Registered`` lists every one of them, all within ``timeout_s``. Every failure to get
there is a ``LinkUnavailable`` naming the endpoint and the reason (refused, TLS, the
server refused our certificate or the registration, no answer in time).

On an open link, ``exchange`` publishes documents and waits for the server's ``Ack`` of
each (at most ``window`` unanswered at once), and ``receive`` reads what the server sends.
Frames that are not what the protocol expects there (garbage, an unexpected document, an
ack for nothing we sent) are counted in ``counts`` and skipped, never fatal; a frame over
``max_frame_bytes`` or a connection lost raises (``Oversize``, ``Malformed``, ``LinkClosed``),
and the link must then be closed.
"""

from __future__ import annotations

import secrets
import ssl
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

import anyio
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from gateway.errors import FrameError, LinkError, LinkUnavailable
from gateway.transports.frames import FrameStream, connect_tls, describe
from gateway.transports.tls import TlsFiles, describe_tls_error, tls_context
from sinks.sweccis.fas import (
    MAX_DOCUMENT_BYTES,
    Ack,
    Document,
    DocumentError,
    Fas,
    OrderDocument,
    Registered,
    encode_register,
    parse_document,
)

__all__ = ["SweccisLink", "SweccisLinkOptions", "tls_problem"]

# OpenSSL alert reasons a server sends when it refuses the client's certificate.
_CERT_REFUSED = ("CERTIFICATE_REQUIRED", "BAD_CERTIFICATE", "UNKNOWN_CA", "CERTIFICATE_UNKNOWN")


class SweccisLinkOptions(BaseModel):
    """Where the SWECCIS server is and the TLS material to reach it (sink and source alike)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    uri: str = Field(description="tls://HOST:PORT of the server's FAS endpoint.")
    ca_file: Path = Field(description="The only CA trusted for the server's certificate.")
    cert_file: Path | None = Field(default=None, description="PEM client certificate (chain).")
    key_file: Path | None = Field(default=None, description="PEM key, if not in cert_file.")
    pkcs12_file: Path | None = Field(default=None, description="Client key and certificate.")
    password_file: Path | None = Field(
        default=None, description="File holding the key's or PKCS#12 password (never inline)."
    )
    server_hostname: str | None = Field(
        default=None, description="Name the server's certificate must carry; default the host."
    )
    client_id: str = Field(
        default="fischer-gateway",
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.:-]{0,127}$",
        description="How this gateway names itself in Register (the certificate identifies it).",
    )
    timeout_s: float = Field(
        default=5.0,
        gt=0,
        le=300,
        description="Deadline to connect and register, and for each acknowledgement awaited.",
    )
    fas_version: Literal[1, 2] = Field(
        default=1,
        description="FAS document version written: 1, or 2 (a merged track as 'merged' "
        "naming the survivor; version 1 writes it as 'lost'). Both are read.",
    )
    max_frame_bytes: int = Field(
        default=MAX_DOCUMENT_BYTES,
        ge=4096,
        le=4 << 20,
        description="Largest document sent or read; a larger frame from the server ends the link.",
    )

    @field_validator("uri")
    @classmethod
    def _tls_uri(cls, value: str) -> str:
        parts = urlsplit(value)
        try:
            port = parts.port
        except ValueError:
            port = None
        if parts.scheme != "tls" or not parts.hostname or not port:
            raise ValueError(f"expected tls://HOST:PORT, got {value!r}")
        if parts.username is not None or parts.password is not None:
            raise ValueError("no credentials in the URI; the client certificate identifies us")
        if parts.path not in ("", "/") or parts.query or parts.fragment:
            raise ValueError(f"expected tls://HOST:PORT and nothing after it, got {value!r}")
        return value

    @model_validator(mode="after")
    def _one_client_certificate(self, info: ValidationInfo) -> SweccisLinkOptions:
        if (self.cert_file is None) == (self.pkcs12_file is None):
            raise ValueError("give exactly one of cert_file (PEM) or pkcs12_file")
        if self.key_file is not None and self.cert_file is None:
            raise ValueError("key_file goes with cert_file")
        if isinstance(info.context, dict) and info.context.get("environment"):
            # On the node (run, check-config): a missing CA or a wrong password is a config
            # error with its line, not a reconnect loop.
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

    @property
    def host(self) -> str:
        """The server's host from ``uri``."""
        return str(urlsplit(self.uri).hostname)

    @property
    def port(self) -> int:
        """The server's port from ``uri``."""
        return int(urlsplit(self.uri).port or 0)

    @property
    def hostname(self) -> str:
        """The name the server's certificate must be valid for."""
        return self.server_hostname or self.host


def tls_problem(files: TlsFiles) -> str | None:
    """Why the TLS material cannot be used, naming the file; None if it loads. Blocking."""
    for path in (files.ca_file, files.cert_file, files.key_file, files.pkcs12_file):
        if path is None:
            continue
        try:
            with path.open("rb"):  # the ssl module's loaders do not name a missing file
                pass
        except OSError as exc:
            return f"{path}: {exc.strerror or exc}"
    try:
        tls_context(files)
    except OSError as exc:
        return f"{exc.filename or files.password_file or files.ca_file}: {exc.strerror or exc}"
    except ssl.SSLError as exc:  # only the CA is loaded without translation
        return f"{files.ca_file}: not a usable CA certificate ({exc.reason or exc})"
    except ValueError as exc:  # names the client certificate or PKCS#12 file
        return str(exc)
    return None


def _refusal(exc: BaseException, options: SweccisLinkOptions) -> str:
    """Why a connection or registration failed, naming the CA, hostname or certificate."""
    reason = describe(exc)
    if isinstance(exc, ssl.SSLCertVerificationError):
        return describe_tls_error(exc, options.tls_files, options.hostname)
    if any(alert in reason for alert in _CERT_REFUSED):
        mine = options.cert_file or options.pkcs12_file
        return f"the server refused the client certificate {mine} ({reason})"
    return reason


class SweccisLink:
    """An open, registered connection; use ``connect`` to make one."""

    def __init__(
        self, frames: FrameStream, options: SweccisLinkOptions, registered: Registered
    ) -> None:
        self.frames = frames
        self.options = options
        self.registered = registered
        self.uri = options.uri
        #: Frames skipped: ``invalid`` (not a document), ``unexpected``, ``stray`` (an ack
        #: for no document in flight).
        self.counts: Counter[str] = Counter()

    @classmethod
    async def connect(
        cls,
        options: SweccisLinkOptions,
        context: ssl.SSLContext,
        *,
        publish: Iterable[Fas] = (),
        subscribe: Iterable[Fas] = (),
    ) -> SweccisLink:
        """Connect, register ``publish``/``subscribe`` and return the link, within ``timeout_s``.

        Raises ``LinkUnavailable`` naming the endpoint and why, for any failure.
        """
        wanted_publish, wanted_subscribe = frozenset(publish), frozenset(subscribe)
        frames: FrameStream | None = None
        uri = options.uri
        try:
            with anyio.fail_after(options.timeout_s):
                stream = await connect_tls(options.host, options.port, context, options.hostname)
                frames = FrameStream(stream, max_frame_bytes=options.max_frame_bytes, link=uri)
                register_id = f"register-{secrets.token_hex(6)}"
                await frames.send(
                    encode_register(
                        register_id,
                        options.client_id,
                        publish=sorted(wanted_publish),
                        subscribe=sorted(wanted_subscribe),
                        version=str(options.fas_version),
                    )
                )
                reply = parse_document(
                    await frames.receive(), source="-", max_bytes=options.max_frame_bytes
                )
        except TimeoutError:
            await _close(frames)
            raise LinkUnavailable(
                uri, f"not registered within {options.timeout_s} s", what=""
            ) from None
        except (OSError, LinkError, FrameError, anyio.BrokenResourceError) as exc:
            await _close(frames)
            raise LinkUnavailable(uri, _refusal(exc, options), what="") from exc
        except BaseException:
            await _close(frames)
            raise
        problem = _registration_problem(reply, register_id, wanted_publish, wanted_subscribe)
        if problem is not None:
            await _close(frames)
            raise LinkUnavailable(uri, problem, what="")
        assert isinstance(reply, Registered)  # noqa: S101 - no problem means Registered
        return cls(frames, options, reply)

    async def send(self, payload: bytes) -> None:
        """Send one document; ``LinkClosed`` or ``Oversize`` (then close the link)."""
        await self.frames.send(payload)

    async def receive(self) -> bytes:
        """The next frame the server sends; ``LinkClosed``, ``Oversize`` or ``Malformed``."""
        return await self.frames.receive()

    async def exchange(self, documents: Sequence[Document], *, window: int) -> dict[str, Ack]:
        """Send ``documents`` (unique ids) and return the server's ack of each, by id.

        At most ``window`` documents wait for their ack at once. Each ack must come within
        ``timeout_s`` of the one before, or of the start (``TimeoutError`` otherwise);
        ``LinkClosed``, ``Oversize`` or ``Malformed`` when the connection fails. After any
        error the link must be closed: what the server had is unknown, so the caller sends it
        all again (the server answers ``duplicate`` for what it had).
        """
        acks: dict[str, Ack] = {}
        pending: set[str] = set()
        sent = 0
        deadline = anyio.current_time() + self.options.timeout_s
        while len(acks) < len(documents):
            while sent < len(documents) and len(pending) < window:
                document = documents[sent]
                await self.frames.send(document.payload)
                pending.add(document.doc_id)
                sent += 1
            # Skipped frames do not extend the wait: only an ack of ours does.
            with anyio.fail_after(max(0.0, deadline - anyio.current_time())):
                data = await self.frames.receive()
            ack = self._ack(data)
            if ack is None:
                continue
            if ack.ref not in pending:
                self.counts["stray"] += 1
                continue
            pending.discard(ack.ref)
            acks[ack.ref] = ack
            deadline = anyio.current_time() + self.options.timeout_s
        return acks

    def _ack(self, data: bytes) -> Ack | None:
        try:
            reply = parse_document(data, source="-", max_bytes=self.options.max_frame_bytes)
        except DocumentError:
            self.counts["invalid"] += 1
            return None
        if not isinstance(reply, Ack):
            self.counts["unexpected"] += 1
            return None
        return reply

    async def aclose(self) -> None:
        """Close the connection without waiting on the server."""
        await self.frames.aclose()


async def _close(frames: FrameStream | None) -> None:
    if frames is not None:
        await frames.aclose()


def _registration_problem(
    reply: Registered | Ack | OrderDocument,
    register_id: str,
    publish: frozenset[Fas],
    subscribe: frozenset[Fas],
) -> str | None:
    if isinstance(reply, Ack) and reply.ref == register_id and reply.status == "rejected":
        return f"registration refused: {reply.reason or 'no reason given'}"
    if not isinstance(reply, Registered) or reply.ref != register_id:
        return f"expected Registered for {register_id}, got {type(reply).__name__}"
    missing = sorted((publish - reply.publish) | (subscribe - reply.subscribe))
    if missing:
        return f"the server did not register {', '.join(missing)}"
    return None
