"""TLS for TAK server streams: the pinned CA, hostname checking and the client certificate.

Verification is always on: the context trusts the configured CA file (the system store only
when a destination asks for it too, ``trust_system_store``), requires a certificate and checks
the hostname; nothing here can turn that off. The client certificate is a PEM pair or a
PKCS#12 bundle, its password read from a file and never logged. ``describe_tls_error`` turns
OpenSSL's verification failures into a sentence that names the CA file or the hostname;
``tls_problem`` says, naming the file, why configured material cannot be used.
"""

from __future__ import annotations

import secrets
import ssl
import tempfile
from dataclasses import dataclass
from pathlib import Path

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.serialization import pkcs12

__all__ = ["TlsFiles", "describe_tls_error", "tls_context", "tls_problem", "unreadable_file"]

# OpenSSL X509_V_ERR_HOSTNAME_MISMATCH and X509_V_ERR_IP_ADDRESS_MISMATCH.
_NAME_MISMATCH = frozenset({62, 64})


@dataclass(frozen=True, slots=True)
class TlsFiles:
    """Where the TLS material of one destination is (paths only; contents are read late)."""

    ca_file: Path
    cert_file: Path | None = None
    key_file: Path | None = None
    pkcs12_file: Path | None = None
    password_file: Path | None = None
    trust_system_store: bool = False


def _password(files: TlsFiles) -> bytes | None:
    if files.password_file is None:
        return None
    # One trailing newline is how editors and `echo` leave it; it is not part of the secret.
    return files.password_file.read_bytes().rstrip(b"\r\n")


def _load_pkcs12(context: ssl.SSLContext, path: Path, password: bytes | None) -> None:
    try:
        key, cert, extra = pkcs12.load_key_and_certificates(path.read_bytes(), password)
    except ValueError:
        raise ValueError(f"{path}: cannot open the PKCS#12 bundle (wrong password?)") from None
    if key is None or cert is None:
        raise ValueError(f"{path}: the PKCS#12 bundle holds no key and certificate")
    # The ssl module loads client chains from files only. The key goes to a private temporary
    # directory encrypted under a one-time password, and is gone when this returns.
    one_time = secrets.token_bytes(32).hex().encode()
    pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.BestAvailableEncryption(one_time),
    ) + b"".join(c.public_bytes(serialization.Encoding.PEM) for c in [cert, *(extra or [])])
    with tempfile.TemporaryDirectory(prefix="fischer-tls-") as tmp:
        chain = Path(tmp) / "client.pem"
        chain.touch(mode=0o600)
        chain.write_bytes(pem)
        context.load_cert_chain(str(chain), password=one_time)


def tls_context(files: TlsFiles) -> ssl.SSLContext:
    """A client context trusting ``files.ca_file``, with the client certificate loaded.

    The system's CA store is trusted as well only when ``files.trust_system_store`` is set.

    Raises ``OSError`` for a missing file, ``ssl.SSLError`` or ``ValueError`` for unusable
    contents; the messages name the file, never the password.
    """
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)  # check_hostname and CERT_REQUIRED
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.load_verify_locations(cafile=str(files.ca_file))
    if files.trust_system_store:
        context.load_default_certs(ssl.Purpose.SERVER_AUTH)
    password = _password(files)
    if files.pkcs12_file is not None:
        _load_pkcs12(context, files.pkcs12_file, password)
    elif files.cert_file is not None:
        key = str(files.key_file) if files.key_file is not None else None
        try:
            context.load_cert_chain(str(files.cert_file), key, password)
        except ssl.SSLError as exc:
            raise ValueError(
                f"{files.cert_file}: cannot load the client certificate and key ({exc.reason})"
            ) from None
    return context


def describe_tls_error(exc: BaseException, files: TlsFiles, hostname: str) -> str:
    """One sentence for a TLS failure, naming the CA file or the hostname where they are why."""
    if isinstance(exc, ssl.SSLCertVerificationError):
        if exc.verify_code in _NAME_MISMATCH:
            return f"the server's certificate is not valid for hostname {hostname!r}"
        trusted = f"the pinned CA {files.ca_file}"
        if files.trust_system_store:
            trusted += " or the system's CA store"
        return f"the server's certificate is not trusted by {trusted} ({exc.verify_message})"
    if isinstance(exc, ssl.SSLError):
        return f"TLS failed: {exc.reason or exc}"
    return f"TLS failed: {exc}"


def unreadable_file(files: TlsFiles) -> str | None:
    """The first TLS file that cannot be read, and why (``path: reason``); None if all can."""
    for path in (
        files.ca_file,
        files.cert_file,
        files.key_file,
        files.pkcs12_file,
        files.password_file,
    ):
        if path is None:
            continue
        try:
            # The ssl module's loaders name no file when one is missing; this does.
            with path.open("rb"):
                pass
        except OSError as exc:
            return f"{path}: {exc.strerror or exc}"
    return None


def tls_problem(files: TlsFiles) -> str | None:
    """Why the TLS material cannot be used, naming the file; None if it loads.

    Reads the files (blocking): call it from a worker thread on the event loop.
    """
    if (unreadable := unreadable_file(files)) is not None:
        return unreadable
    try:
        tls_context(files)
    except OSError as exc:
        return f"{exc.filename or files.ca_file}: {exc.strerror or exc}"
    except ssl.SSLError as exc:  # only the CA is loaded without translation
        return f"{files.ca_file}: not a usable CA certificate ({exc.reason or exc})"
    except ValueError as exc:  # names the client certificate or PKCS#12 file
        return str(exc)
    return None
