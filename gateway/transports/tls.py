"""TLS for TAK server streams: the pinned CA, hostname checking and the client certificate.

Verification is always on: the context trusts only the configured CA file (not the system
store), requires a certificate and checks the hostname; nothing here can turn that off. The
client certificate is a PEM pair or a PKCS#12 bundle, its password read from a file and never
logged. ``describe_tls_error`` turns OpenSSL's verification failures into a sentence that
names the CA file or the hostname.
"""

from __future__ import annotations

import secrets
import ssl
import tempfile
from dataclasses import dataclass
from pathlib import Path

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.serialization import pkcs12

__all__ = ["TlsFiles", "describe_tls_error", "tls_context"]

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
    """A client context trusting only ``files.ca_file``, with the client certificate loaded.

    Raises ``OSError`` for a missing file, ``ssl.SSLError`` or ``ValueError`` for unusable
    contents; the messages name the file, never the password.
    """
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)  # check_hostname and CERT_REQUIRED
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.load_verify_locations(cafile=str(files.ca_file))
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
        return (
            f"the server's certificate is not trusted by the pinned CA {files.ca_file} "
            f"({exc.verify_message})"
        )
    if isinstance(exc, ssl.SSLError):
        return f"TLS failed: {exc.reason or exc}"
    return f"TLS failed: {exc}"
