"""The NFFI sink: own airframes and relayed friendly reports as NFFI 1.3 tracks (STANAG 5527).

Each batch becomes one ``NFFIMessage`` document (``sinks.nffi.codec``; docs/nffi.md has the
mapping and the framing) holding a track per ``Telemetry`` with a position and per
``BlueForce``. It goes to a ground C2 system over **IP1** (``uri``: ``tcp://HOST:PORT``, or
``tls://HOST:PORT`` with a client certificate, the CA pinned and the hostname verified),
documents back to back on one connection, and/or is appended to a file (``path``), documents
back to back, each ending in a newline. A track identity is its trackSource plus its
``dateTime`` (whole seconds), so a unit's second report within the same second is not sent:
at most one track per unit per second goes out (the newest times of ``MAX_UNITS`` units are
remembered).

A failure raises ``TransientSinkError`` naming the sink and the destination, and the
SinkRunner retries the batch: a receiver keeps the newest ``dateTime`` per trackSource, so a
repeated document (in the file too) changes nothing. The connection reads what the peer
sends only to notice that it hung up (one immediate reconnect); IP1 defines no answer.
"""

from __future__ import annotations

import os
import socket
import ssl
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path
from urllib.parse import urlsplit

import anyio
import anyio.to_thread
import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from gateway.c2.sink import SinkConfig
from gateway.domain.geoid import bundled_geoid
from gateway.errors import TransientSinkError
from gateway.events import BlueForce, Event, EventKind, Telemetry
from gateway.ops.logsetup import RateLimit
from gateway.transports.stream import open_tcp, send_all, start_tls
from gateway.transports.tls import TlsFiles, describe_tls_error, tls_context, tls_problem
from sinks.nffi.codec import (
    NffiOptions,
    encode_message,
    encode_track,
    nffi_time,
    track_uid,
)

__all__ = ["MAX_UNITS", "NffiSink", "NffiSinkConfig", "NffiTls"]

log = structlog.get_logger(__name__)

#: Units whose last sent ``dateTime`` is remembered (the one heard from longest ago goes first).
MAX_UNITS = 4096
_KINDS = frozenset({EventKind.TELEMETRY, EventKind.BLUE_FORCE})
_READ_CHUNK = 65_536
_MAX_DRAIN = 1 << 20
_FILE_MODE = 0o640
_FROZEN = ConfigDict(frozen=True, extra="forbid")


class NffiTls(BaseModel):
    """The client certificate (PEM) and the pinned CA of the IP1 peer."""

    model_config = _FROZEN

    ca_file: Path = Field(description="The only CA trusted for the peer's certificate.")
    cert_file: Path = Field(description="PEM client certificate (chain).")
    key_file: Path | None = Field(default=None, description="PEM key, if not in cert_file.")
    password_file: Path | None = Field(default=None, description="File holding the key password.")
    server_hostname: str | None = Field(
        default=None, description="Name the peer's certificate must carry; defaults to the host."
    )

    def files(self) -> TlsFiles:
        """The files as the TLS transport takes them."""
        return TlsFiles(self.ca_file, self.cert_file, self.key_file, None, self.password_file)

    @model_validator(mode="after")
    def _loadable(self, info: ValidationInfo) -> NffiTls:
        if isinstance(info.context, dict) and info.context.get("environment"):
            problem = tls_problem(self.files())
            if problem is not None:
                raise ValueError(problem)
        return self


class NffiSinkConfig(SinkConfig):
    """Options of the NFFI sink: where documents go and who releases the tracks."""

    uri: str | None = Field(
        default=None, description="IP1 peer: tcp://HOST:PORT, or tls://HOST:PORT with 'tls'."
    )
    tls: NffiTls | None = Field(default=None, description="Required for tls://, only for it.")
    path: Path | None = Field(default=None, description="Append each document to this file.")
    fsync: bool = Field(default=False, description="fsync the file after every document.")
    kinds: frozenset[EventKind] = Field(
        default=_KINDS, min_length=1, description="telemetry (own airframes), blue_force."
    )
    system: str = Field(
        default="FISCHER-GW",
        pattern=r"^[A-Za-z0-9.,:*\-]{1,30}$",
        description="trackSource system: the releasing system (NFFI identity).",
    )
    country: str | None = Field(
        default=None, pattern=r"^[A-Z]{3}$", description="trackSource country (e.g. SWE)."
    )
    subsystem: str | None = Field(
        default=None, pattern=r"^[A-Za-z0-9.,:*\-]{1,30}$", description="trackSource subsystem."
    )
    sec_policy_name: str | None = Field(
        default=None, max_length=256, description="secPolicyName label (e.g. NATO)."
    )
    sec_classification: str | None = Field(
        default=None, min_length=1, max_length=30, description="secClassification label."
    )
    connect_timeout_s: float = Field(default=5.0, gt=0, description="Deadline of a connect.")

    @field_validator("kinds")
    @classmethod
    def _known_kinds(cls, value: frozenset[EventKind]) -> frozenset[EventKind]:
        if extra := value - _KINDS:
            raise ValueError(
                f"NFFI carries telemetry and blue_force, not {sorted(k.value for k in extra)}"
            )
        return value

    @field_validator("uri")
    @classmethod
    def _check_uri(cls, value: str | None) -> str | None:
        if value is None:
            return None
        parts = urlsplit(value)
        try:
            port = parts.port
        except ValueError:
            port = None
        if parts.scheme not in ("tcp", "tls") or not parts.hostname or not port:
            raise ValueError(f"expected tcp://HOST:PORT or tls://HOST:PORT, got {value!r}")
        return value

    @model_validator(mode="after")
    def _somewhere(self) -> NffiSinkConfig:
        if self.uri is None and self.path is None:
            raise ValueError("give uri (IP1 over TCP/TLS), path (a file) or both")
        is_tls = self.uri is not None and self.uri.startswith("tls://")
        if is_tls != (self.tls is not None):
            raise ValueError("a 'tls' section goes with a tls:// uri and only with it")
        return self


class NffiSink:
    """Writes NFFI documents to an IP1 peer and/or a file."""

    config_model = NffiSinkConfig

    def __init__(self, name: str, config: NffiSinkConfig) -> None:
        self.name = name
        self.config = config
        self.options = NffiOptions(
            system=config.system,
            country=config.country,
            subsystem=config.subsystem,
            sec_policy_name=config.sec_policy_name,
            sec_classification=config.sec_classification,
            geoid=bundled_geoid().undulation,
        )
        parts = urlsplit(config.uri or "")
        self.host, self.port = str(parts.hostname or ""), int(parts.port or 0)
        self._sock: socket.socket | None = None
        self._context: ssl.SSLContext | None = None
        self._fd: int | None = None
        self._sent: OrderedDict[str, str] = OrderedDict()
        #: Documents written to the peer and to the file, reconnects after the peer hung up.
        self.documents = 0
        self.reconnects = 0
        self._log_limit = RateLimit(interval_s=30.0)
        self.log = log.bind(sink=name, uri=config.uri, path=str(config.path or ""))

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Telemetry and blue force unless the config narrows them."""
        return self.config.kinds

    def own_uids(self, airframes: Sequence[str]) -> frozenset[str]:
        """The uids our tracks of ``airframes`` get when an NFFI source reads them back."""
        return frozenset(track_uid(self.options, airframe) for airframe in airframes)

    def _fail(self, where: str, what: str) -> TransientSinkError:
        return TransientSinkError(f"sink {self.name}: {where}: {what}", sink=self.name)

    # -- the file --------------------------------------------------------------------------

    def _open_file(self) -> int:
        path = self.config.path
        assert path is not None  # noqa: S101 - only called with a path
        return os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, _FILE_MODE)

    def _write_file(self, document: bytes) -> None:
        if self._fd is None:
            self._fd = self._open_file()
        view = memoryview(document)
        while view:
            view = view[os.write(self._fd, view) :]
        if self.config.fsync:
            os.fsync(self._fd)

    # -- the IP1 connection ----------------------------------------------------------------

    async def _connect(self) -> None:
        raw: socket.socket | None = None
        tls = self.config.tls
        hostname = (tls.server_hostname if tls else None) or self.host
        try:
            with anyio.fail_after(self.config.connect_timeout_s):
                raw = await open_tcp(self.host, self.port)
                if tls is not None:
                    if self._context is None:
                        self._context = await anyio.to_thread.run_sync(tls_context, tls.files())
                    sock: socket.socket = await start_tls(raw, self._context, hostname)
                else:
                    sock = raw
        except TimeoutError:
            self._discard(raw)
            raise self._fail(
                str(self.config.uri), f"no connection within {self.config.connect_timeout_s} s"
            ) from None
        except ssl.SSLError as exc:
            self._discard(raw)
            assert tls is not None  # noqa: S101 - only TLS raises SSLError
            raise self._fail(
                str(self.config.uri), describe_tls_error(exc, tls.files(), hostname)
            ) from exc
        except (OSError, ValueError) as exc:
            self._discard(raw)
            raise self._fail(str(self.config.uri), f"cannot connect: {exc}") from exc
        except BaseException:
            self._discard(raw)
            raise
        self._sock = sock
        self.log.info("nffi_peer_connected", tls=tls is not None)

    @staticmethod
    def _discard(sock: socket.socket | None) -> None:
        if sock is not None:
            sock.close()

    def _peer_closed(self) -> bool:
        """Read (and drop) what the peer sent; True if it has hung up."""
        assert self._sock is not None  # noqa: S101 - connected
        for _ in range(_MAX_DRAIN // _READ_CHUNK):
            try:
                if not self._sock.recv(_READ_CHUNK):
                    return True
            except (BlockingIOError, ssl.SSLWantReadError, ssl.SSLWantWriteError):
                return False
            except OSError:
                return True
        return False

    async def _write(self, data: bytes) -> None:
        assert self._sock is not None  # noqa: S101 - connected
        done = False
        try:
            await send_all(self._sock, data)
            done = True
        finally:
            if not done:
                self._close_peer()  # half a document would corrupt the stream after it

    def _close_peer(self) -> None:
        self._discard(self._sock)
        self._sock = None

    async def _send_peer(self, document: bytes) -> None:
        if self._sock is not None and self._peer_closed():
            self.reconnects += 1
            self.log.info("nffi_peer_reconnecting", reason="the peer closed the stream")
            self._close_peer()
        if self._sock is None:
            await self._connect()
        try:
            await self._write(document)
        except OSError as exc:
            self._close_peer()
            raise self._fail(str(self.config.uri), f"connection lost: {exc}") from exc

    # -- the sink contract -----------------------------------------------------------------

    async def open(self) -> None:
        """Open the file and connect; ``TransientSinkError`` naming what failed."""
        if self.config.path is not None and self._fd is None:
            try:
                self._fd = await anyio.to_thread.run_sync(self._open_file)
            except OSError as exc:
                raise self._fail(str(self.config.path), exc.strerror or str(exc)) from exc
        if self.config.uri is not None and self._sock is None:
            await self._connect()

    def _tracks(self, batch: Sequence[Event]) -> tuple[list[str], dict[str, str]]:
        """The batch's track elements, one per unit and second, and the times they carry."""
        chosen: dict[str, tuple[str, str]] = {}
        for event in batch:
            if event.kind not in self.config.kinds:
                continue
            if isinstance(event, Telemetry):
                unit = "own:" + event.airframe
            elif isinstance(event, BlueForce):
                unit = "blue:" + event.uid
            else:
                continue
            stamp = nffi_time(event.time)
            if self._sent.get(unit) == stamp:
                continue  # the same trackSource and dateTime already went out
            track = encode_track(event, self.options)
            if track is not None:
                chosen[unit] = (stamp, track)  # the newest of the batch per unit
        return [t for _, t in chosen.values()], {u: s for u, (s, _) in chosen.items()}

    async def send(self, batch: Sequence[Event]) -> None:
        """Write one document of the batch's tracks to the file and the peer, or raise."""
        tracks, stamps = self._tracks(batch)
        if not tracks:
            return
        document = encode_message(tracks)
        if self.config.path is not None:
            try:
                await anyio.to_thread.run_sync(self._write_file, document)
            except OSError as exc:
                raise self._fail(str(self.config.path), exc.strerror or str(exc)) from exc
        if self.config.uri is not None:
            await self._send_peer(document)
        self.documents += 1
        for unit, stamp in stamps.items():
            self._sent[unit] = stamp
            self._sent.move_to_end(unit)
        while len(self._sent) > MAX_UNITS:
            self._sent.popitem(last=False)

    async def aclose(self) -> None:
        """Close the connection and the file; safe before ``open`` and after a failed one."""
        self._close_peer()
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)
