"""The options of one HTTPS C2 endpoint, shared by the sinks and sources that talk to it.

``HttpsClientOptions`` is a pydantic options model (frozen, unknown keys refused) holding the
pinned CA, the client certificate and a deadline; ``HttpsEndpoint`` adds a base URL
(``https://`` only, no credentials, query or fragment) that fixed paths are appended to.
Subclass either together with ``SinkConfig`` for a sink, or alone for a source. On the node
(validation context ``{"environment": True}``: ``run`` and ``check-config``) the validator
loads the TLS material, so a missing CA or a wrong password is a config error naming the
file and its line, not a retry loop at the first request.
"""

from __future__ import annotations

from pathlib import Path
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from gateway.transports.tls import TlsFiles, tls_problem

__all__ = ["HttpsClientOptions", "HttpsEndpoint", "check_https_url"]


def check_https_url(value: str, *, allow_query: bool = False) -> str:
    """``value`` if it is ``https://HOST[:PORT][/PATH]``, else ``ValueError`` saying why.

    A query is refused unless ``allow_query`` (a full URL, not a base that paths follow).
    """
    parts = urlsplit(value)
    try:
        port = parts.port
    except ValueError:
        port = -1
    if parts.scheme != "https" or not parts.hostname or port == -1:
        raise ValueError("expected https://HOST[:PORT][/PATH]")
    if parts.username is not None or parts.password is not None:
        raise ValueError("no credentials in the URL; the client certificate identifies us")
    if parts.query and not allow_query:
        raise ValueError("no query in a base URL; the paths below it are fixed")
    if parts.fragment:
        raise ValueError("a fragment is never sent: drop it")
    return value


class HttpsClientOptions(BaseModel):
    """The TLS material and the deadline of an HTTPS client with a client certificate."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    ca_file: Path = Field(description="The CA pinned for the server's certificate.")
    trust_system_store: bool = Field(
        default=False,
        description="Also trust the system's CA store (off: only ca_file is trusted).",
    )
    cert_file: Path | None = Field(default=None, description="PEM client certificate (chain).")
    key_file: Path | None = Field(default=None, description="PEM key, if not in cert_file.")
    pkcs12_file: Path | None = Field(default=None, description="Client key and certificate.")
    password_file: Path | None = Field(
        default=None, description="File holding the key's or PKCS#12 password (never inline)."
    )
    timeout_s: float = Field(
        default=5.0,
        gt=0,
        le=300,
        description="Deadline of each request, whole: connect, send and read the answer.",
    )

    @model_validator(mode="after")
    def _one_client_certificate(self, info: ValidationInfo) -> HttpsClientOptions:
        if (self.cert_file is None) == (self.pkcs12_file is None):
            raise ValueError("give exactly one of cert_file (PEM) or pkcs12_file")
        if self.key_file is not None and self.cert_file is None:
            raise ValueError("key_file goes with cert_file")
        if isinstance(info.context, dict) and info.context.get("environment"):
            # On the node (run, check-config): read the files now, so a missing CA or a wrong
            # password is a config error with its line, not a retry loop at the first request.
            problem = tls_problem(self.tls_files)
            if problem is not None:
                raise ValueError(problem)
        return self

    @property
    def tls_files(self) -> TlsFiles:
        """The TLS material as the transports take it (paths only)."""
        return TlsFiles(
            self.ca_file,
            self.cert_file,
            self.key_file,
            self.pkcs12_file,
            self.password_file,
            self.trust_system_store,
        )


class HttpsEndpoint(HttpsClientOptions):
    """Where one HTTPS C2 server listens (a base URL) and the TLS material to reach it."""

    base_url: str = Field(
        description="https://HOST[:PORT][/PATH]; the endpoints' paths are appended to it."
    )

    @field_validator("base_url")
    @classmethod
    def _https_only(cls, value: str) -> str:
        return check_https_url(value).rstrip("/")

    def url(self, path: str) -> str:
        """The URL of ``path`` (starting with ``/``) below ``base_url``."""
        return self.base_url + path
