"""How the ``nats`` sink and source reach their NATS server: options and the connection.

Credentials are files, never the YAML: a client certificate and key (TLS, the CA pinned),
a user credentials file (``.creds``: JWT and NKey seed) or a token file. The connection is
made for a daemon: it reconnects for ever (nats-py's default gives up after about two
minutes), pings every ``ping_interval_s`` so a dead peer is noticed, and reports
disconnects and errors to the log at most every 10 s.
"""

from __future__ import annotations

import asyncio
import re
import ssl
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import nats
import structlog
from nats.aio.client import Client
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from gateway.ops.logsetup import RateLimit
from gateway.transports.tls import TlsFiles, tls_context, tls_problem
from sinks.nats.subjects import NODE_PATTERN

__all__ = ["NatsServer", "NatsTls", "connect"]

log = structlog.get_logger(__name__)

_FROZEN = ConfigDict(frozen=True, extra="forbid")


class NatsTls(BaseModel):
    """TLS to the NATS server: the pinned CA and this node's client certificate (PEM files)."""

    model_config = _FROZEN

    ca_file: Path = Field(description="The only CA trusted for the server's certificate.")
    cert_file: Path = Field(description="PEM client certificate (chain) of this node.")
    key_file: Path | None = Field(default=None, description="PEM key, if not in cert_file.")
    password_file: Path | None = Field(default=None, description="File holding the key password.")

    def files(self) -> TlsFiles:
        """The files as the TLS transport takes them."""
        return TlsFiles(self.ca_file, self.cert_file, self.key_file, None, self.password_file)

    def context(self) -> ssl.SSLContext:
        """A client context: the CA pinned, the hostname verified, the certificate loaded."""
        return tls_context(self.files())

    @model_validator(mode="after")
    def _loadable(self, info: ValidationInfo) -> NatsTls:
        if isinstance(info.context, dict) and info.context.get("environment"):
            problem = tls_problem(self.files())
            if problem is not None:
                raise ValueError(problem)
        return self


def _url_problem(url: str) -> str | None:
    """Why ``url`` is no server URL nats-py could connect to, or None. Checked with the
    config, not at the first connect: a bad one would otherwise be retried for ever."""
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 - raises for a port that is not one
    except ValueError as exc:
        return f"{url[:200]!r}: not a URL ({exc})"
    if parts.username is not None or parts.password is not None:
        # It would be logged with every connect failure, and secrets are files.
        return "a server URL carries no user or password: use creds_file or token_file"
    if not parts.hostname:
        return f"{url[:200]!r}: no host"
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        return f"{url[:200]!r}: only nats://HOST:PORT or tls://HOST:PORT"
    return None


class NatsServer(BaseModel):
    """Where this node's NATS server is and how to authenticate to it."""

    model_config = _FROZEN

    node: str = Field(
        pattern=NODE_PATTERN,
        description="This gateway node's name: the subject token of what it publishes, the "
        "part of its stream names, and its JetStream domain in the server's config.",
    )
    servers: list[str] = Field(
        default=["nats://127.0.0.1:4222"],
        min_length=1,
        max_length=16,
        description="URLs of this node's NATS server (nats:// or tls://), normally loopback.",
    )
    tls: NatsTls | None = Field(default=None, description="Client certificate TLS, if used.")
    creds_file: Path | None = Field(
        default=None, description="NATS user credentials file (JWT and NKey seed)."
    )
    token_file: Path | None = Field(default=None, description="File holding an auth token.")
    connect_timeout_s: float = Field(default=2.0, gt=0, le=60, description="Per connect try.")
    ping_interval_s: float = Field(
        default=10.0, gt=0, le=300, description="Ping period: a silent server is found this fast."
    )
    pending_bytes: int = Field(
        default=8 * 1024 * 1024,
        ge=64 * 1024,
        le=256 * 1024 * 1024,
        description="What the client buffers while disconnected; the spool holds the rest.",
    )
    request_timeout_s: float = Field(
        default=5.0, gt=0, le=120, description="Deadline of a JetStream API call or publish ack."
    )

    @field_validator("node", mode="before")
    @classmethod
    def _node(cls, node: object) -> object:
        # Before the pattern, so the error says what a node name is in words.
        if isinstance(node, str) and not re.fullmatch(NODE_PATTERN, node):
            raise ValueError("a node name is 1-32 letters, digits, '_' or '-'")
        return node

    @field_validator("servers")
    @classmethod
    def _urls(cls, servers: list[str]) -> list[str]:
        for url in servers:
            if not url.startswith(("nats://", "tls://")):
                raise ValueError(f"{url[:200]!r}: a server URL starts with nats:// or tls://")
            problem = _url_problem(url)
            if problem is not None:
                raise ValueError(problem)
        return servers

    @field_validator("creds_file", "token_file")
    @classmethod
    def _secret_file(cls, path: Path | None, info: ValidationInfo) -> Path | None:
        # Checked per key, so the error names creds_file or token_file and its line.
        environment = isinstance(info.context, dict) and info.context.get("environment")
        if path is not None and environment and not path.is_file():
            raise ValueError("no such file")
        return path

    @model_validator(mode="after")
    def _one_secret(self) -> NatsServer:
        if self.creds_file is not None and self.token_file is not None:
            raise ValueError("creds_file and token_file: give one of them, not both")
        return self


async def connect(server: NatsServer, name: str) -> Client:
    """A connection to ``server`` for a daemon; raises ``OSError``/nats errors on failure."""
    limit = RateLimit(interval_s=10.0)

    async def disconnected() -> None:
        if limit.allow("disconnected"):
            log.warning("nats_disconnected", component=name, node=server.node)

    async def reconnected() -> None:
        log.info("nats_reconnected", component=name, node=server.node)

    async def error(exc: Exception) -> None:
        if limit.allow("error"):
            log.warning("nats_error", component=name, error=str(exc)[:200])

    options: dict[str, Any] = {
        "servers": list(server.servers),
        "name": f"fischer-gateway {server.node} {name}",
        "connect_timeout": server.connect_timeout_s,
        "max_reconnect_attempts": -1,
        "reconnect_time_wait": 0.5,
        "ping_interval": server.ping_interval_s,
        "max_outstanding_pings": 2,
        "pending_size": server.pending_bytes,
        "allow_reconnect": True,
        "disconnected_cb": disconnected,
        "reconnected_cb": reconnected,
        "error_cb": error,
    }
    if server.tls is not None:
        options["tls"] = server.tls.context()
    if server.creds_file is not None:
        options["user_credentials"] = str(server.creds_file)
    if server.token_file is not None:
        options["token"] = server.token_file.read_text().strip()
    # nats-py retries the first connect as often as a reconnect (for ever here): bound it,
    # and let the caller's own retry (the sink runner's backoff, the source's loop) go on.
    try:
        return await asyncio.wait_for(nats.connect(**options), server.connect_timeout_s * 2 + 1)
    except TimeoutError:
        raise TimeoutError(f"no answer from {', '.join(server.servers)}") from None
