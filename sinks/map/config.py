"""The map sink's options (``sinks[].options``), and the rule for binding beyond loopback.

Loopback (``127.0.0.0/8``, ``::1``, ``localhost``) is the default and needs nothing more.
Bound anywhere else the page and its stream carry the whole operational picture, so the
config is refused at load unless every client must prove itself: a ``token_file`` (the token
in an ``Authorization: Bearer`` header, or once in the page's address, then a cookie), or
``tls`` with a ``client_ca_file`` (a client certificate that CA signed), or both.
"""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from gateway.c2.sink import SinkConfig
from gateway.events import EventKind

__all__ = ["MIN_TOKEN_CHARS", "MapSinkConfig", "MapTiles", "MapTls", "is_loopback", "read_token"]

MIN_TOKEN_CHARS = 16
_MAX_TOKEN_CHARS = 512

#: The kinds the map shows by default: all it can draw.
DEFAULT_KINDS = frozenset(
    {
        EventKind.TELEMETRY,
        EventKind.LINK_STATE,
        EventKind.DETECTION,
        EventKind.TRACK,
        EventKind.BLUE_FORCE,
        EventKind.HANDOFF,
        EventKind.ORDER,
        EventKind.ORDER_STATUS,
    }
)


def is_loopback(host: str) -> bool:
    """True for a loopback address or ``localhost``; False for any other name or address."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a name may resolve anywhere


def read_token(path: Path) -> str:
    """The token in ``path`` (surrounding whitespace ignored); ``ValueError`` if unfit."""
    with path.open("rb") as handle:
        raw = handle.read(_MAX_TOKEN_CHARS + 2)
    try:
        token = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        raise ValueError(f"token_file {path}: not ASCII text") from None
    if len(token) > _MAX_TOKEN_CHARS:
        raise ValueError(f"token_file {path}: longer than {_MAX_TOKEN_CHARS} characters")
    if len(token) < MIN_TOKEN_CHARS or not token.isprintable() or " " in token:
        raise ValueError(
            f"token_file {path}: the token must be at least {MIN_TOKEN_CHARS} printable "
            "characters without spaces (e.g. the output of `openssl rand -hex 24`)"
        )
    return token


class MapTls(BaseModel):
    """HTTPS for the map: the node's certificate and, to require client certificates, a CA."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    cert_file: Path = Field(description="The listener's certificate chain (PEM).")
    key_file: Path = Field(description="Its private key (PEM).")
    client_ca_file: Path | None = Field(
        default=None, description="CA (PEM) a browser's client certificate must chain to."
    )

    @model_validator(mode="after")
    def _files_exist(self, info: ValidationInfo) -> MapTls:
        on_node = isinstance(info.context, dict) and info.context.get("environment")
        if on_node:
            for key in ("cert_file", "key_file", "client_ca_file"):
                path = getattr(self, key)
                if path is not None and not path.is_file():
                    raise ValueError(f"{key} {path} is not a readable file")
        return self


class MapTiles(BaseModel):
    """A local raster base map: a directory of ``z/x/y`` tiles or an MBTiles file."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    path: Path = Field(description="A directory of z/x/y.<format> files, or an .mbtiles file.")
    format: Literal["png", "jpg", "jpeg", "webp"] = Field(
        default="png", description="The files' format in a directory (an MBTiles file says)."
    )
    min_zoom: int | None = Field(default=None, ge=0, le=24, description="Lowest zoom served.")
    max_zoom: int | None = Field(default=None, ge=0, le=24, description="Highest zoom served.")
    attribution: str = Field(
        default="", max_length=200, description="Credit shown on the map (plain text)."
    )

    @model_validator(mode="after")
    def _usable(self, info: ValidationInfo) -> MapTiles:
        low, high = self.min_zoom, self.max_zoom
        if low is not None and high is not None and low > high:
            raise ValueError("min_zoom is above max_zoom")
        on_node = isinstance(info.context, dict) and info.context.get("environment")
        if on_node and not (self.path.is_dir() or self.path.is_file()):
            raise ValueError(f"path {self.path} is neither a directory nor a file")
        return self


class MapSinkConfig(SinkConfig):
    """Options of the map sink."""

    host: str = Field(default="127.0.0.1", min_length=1, description="Address to listen on.")
    port: int = Field(default=8780, ge=0, le=65535, description="TCP port; 0 picks a free one.")
    token_file: Path | None = Field(
        default=None, description="File holding the access token clients must present."
    )
    tls: MapTls | None = Field(
        default=None, description="Serve HTTPS with this certificate (and client certificates)."
    )
    allowed_hosts: tuple[str, ...] = Field(
        default=(),
        max_length=32,
        description="Host names the page may be reached by, beside the listen address "
        "(browsers send it as Host; others are refused, against DNS rebinding).",
    )
    title: str = Field(default="Fischer gateway", max_length=80, description="The page's title.")
    kinds: frozenset[EventKind] = Field(
        default=DEFAULT_KINDS, description="Event kinds the map takes (of those it can draw)."
    )
    max_connections: int = Field(
        default=32, ge=1, le=1024, description="Requests and streams served at once."
    )
    queue_max: int = Field(
        default=2048, ge=16, le=65536, description="Changes queued per stream before it is cut."
    )
    keepalive_s: float = Field(
        default=15.0, gt=0, le=300, description="A comment line on idle streams this often (s)."
    )
    stall_s: float = Field(
        default=60.0,
        ge=1,
        le=3600,
        description="A connection whose client has taken nothing sent to it for this long is "
        "aborted (s; Linux's TCP_USER_TIMEOUT).",
    )
    max_airframes: int = Field(
        default=500, ge=1, le=10_000, description="Airframes kept; the oldest go first."
    )
    max_tracks: int = Field(
        default=2000, ge=1, le=50_000, description="Tracks kept; the oldest go first."
    )
    max_blue: int = Field(
        default=2000, ge=1, le=50_000, description="Friendly units kept; the oldest go first."
    )
    max_cues: int = Field(
        default=500, ge=1, le=10_000, description="GUTE II cues kept; the oldest go first."
    )
    max_orders: int = Field(
        default=500, ge=1, le=10_000, description="Orders kept; the oldest go first."
    )
    max_detections: int = Field(
        default=500, ge=0, le=50_000, description="Newest detections drawn (0: none)."
    )
    history_points: int = Field(
        default=20, ge=1, le=500, description="Past positions drawn behind each track."
    )
    cue_revisions: int = Field(
        default=10, ge=1, le=100, description="Revisions kept per GUTE II cue."
    )
    expire_after_s: float = Field(
        default=900.0, gt=0, description="An entity unheard this long leaves the map (s)."
    )

    archive: Path | None = Field(
        default=None,
        description="The live file of a jsonl sink (its `path`): the time slider replays it.",
    )
    replay_max_mb: int = Field(
        default=64, ge=1, le=4096, description="Archive read per time-slider request (MiB)."
    )
    replay_max_s: float = Field(
        default=10.0, gt=0, le=120, description="Time spent per time-slider request (s)."
    )
    tiles: MapTiles | None = Field(
        default=None, description="Local raster tiles as the base map (else world-atlas)."
    )

    @field_validator("kinds")
    @classmethod
    def _drawable(cls, kinds: frozenset[EventKind]) -> frozenset[EventKind]:
        if not kinds:
            raise ValueError("give at least one kind")
        other = sorted(k.value for k in kinds - DEFAULT_KINDS)
        if other:
            raise ValueError(f"the map cannot show {', '.join(other)}")
        return kinds

    @model_validator(mode="after")
    def _guarded_beyond_loopback(self) -> MapSinkConfig:
        if is_loopback(self.host):
            return self
        if self.token_file is None and (self.tls is None or self.tls.client_ca_file is None):
            raise ValueError(
                f"host {self.host} is not loopback: anyone who reaches it would see the "
                "picture, so give token_file, or tls with client_ca_file (client "
                "certificates), or both"
            )
        return self
