"""The one exception hierarchy of fischer-gateway.

Every error the gateway raises on purpose is a ``GatewayError``; foreign exceptions are
translated once, at the boundary where they enter, with ``raise ... from exc``::

    GatewayError
    ├── ConfigError                  a config file or value is wrong (carries every issue found)
    ├── LinkError                    a transport to an airframe failed
    │   ├── LinkClosed               the peer closed the stream (leads to a reconnect)
    │   └── LinkUnavailable          the transport could not be opened (bind, connect, device)
    ├── FrameError                   bytes read from a link could not become a frame
    │   ├── Malformed                not a frame: bad magic, length or CRC
    │   ├── Oversize                 larger than the configured bound
    │   ├── AuthenticationFailed     tag or signature did not verify
    │   └── Replayed                 a frame already seen, or too old
    ├── SinkError                    an output sink could not take events
    │   ├── TransientSinkError       try again later (the SinkRunner retries with backoff)
    │   ├── PermanentSinkError       these events will never be accepted (dead-lettered)
    │   └── SinkLoadError            the sink named in config cannot be loaded or configured
    ├── SpoolError                   the spool database cannot be opened or written
    ├── HttpAnswerError              a server's HTTP answer is not HTTP/1.1 within our bounds
    ├── OrderRejected                an order failed its acceptance checks
    └── ScoreInputError              a truth file or archive given to the scorer is unusable

Errors carry structured attributes (``key_path``, ``line``, ``airframe``, ``sink``, ``link``)
so a log line can bind them instead of parsing the message.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

__all__ = [
    "AuthenticationFailed",
    "ConfigError",
    "ConfigIssue",
    "FrameError",
    "GatewayError",
    "HttpAnswerError",
    "LinkClosed",
    "LinkError",
    "LinkUnavailable",
    "Malformed",
    "OrderRejected",
    "Oversize",
    "PermanentSinkError",
    "Replayed",
    "ScoreInputError",
    "SinkError",
    "SinkLoadError",
    "SinkOptionsInvalid",
    "SpoolError",
    "TransientSinkError",
    "os_reason",
]


class GatewayError(Exception):
    """Base of every error fischer-gateway raises on purpose."""


@dataclass(frozen=True, slots=True)
class ConfigIssue:
    """One problem found in a config file: where it is and what was wrong."""

    source: str
    line: int | None
    key_path: str
    message: str

    def __str__(self) -> str:
        where = f"{self.source}:{self.line}" if self.line is not None else self.source
        return f"{where} {self.key_path}: {self.message}"


class ConfigError(GatewayError, ValueError):
    """Raised when a config file cannot be read or fails validation.

    Holds every issue found, not just the first, so an operator fixes them in one pass.
    """

    def __init__(self, issues: list[ConfigIssue]) -> None:
        self.issues = list(issues)
        super().__init__("\n".join(str(issue) for issue in self.issues))


class LinkError(GatewayError, OSError):
    """Raised when a transport to an airframe fails."""

    def __init__(self, link: str, message: str, *, what: str = "link") -> None:
        self.link = link
        super().__init__(f"{what} {link}: {message}" if what else f"{link}: {message}")


class LinkClosed(LinkError):
    """Raised when the peer of a stream link closed it (EOF); the link reconnects."""


class LinkUnavailable(LinkError):
    """Raised when a link cannot be opened: address in use, refused, device missing."""


class FrameError(GatewayError, ValueError):
    """Raised when bytes read from a link cannot become a frame. Counted by ``reason``."""

    reason = "malformed"

    def __init__(self, message: str, *, link: str | None = None) -> None:
        self.link = link
        super().__init__(message)


class Malformed(FrameError):
    """Raised for bytes that are not a frame: bad magic, length or checksum."""

    reason = "malformed"


class Oversize(FrameError):
    """Raised when a datagram or frame is larger than the configured bound."""

    reason = "oversize"

    def __init__(self, size: int, limit: int, *, link: str | None = None) -> None:
        self.size = size
        self.limit = limit
        super().__init__(f"{size} bytes exceeds the {limit}-byte limit", link=link)


class AuthenticationFailed(FrameError):
    """Raised when a frame's AEAD tag or MAVLink 2 signature does not verify."""

    reason = "auth"


class Replayed(FrameError):
    """Raised when a frame was already seen or is older than the replay window."""

    reason = "replay"


class SinkError(GatewayError):
    """Raised by, or about, an output sink; ``sink`` names it."""

    def __init__(self, message: str, *, sink: str | None = None) -> None:
        self.sink = sink
        super().__init__(message)


class TransientSinkError(SinkError):
    """Raised by a sink that could not deliver now but may later; the runner retries."""


class PermanentSinkError(SinkError):
    """Raised by a sink that will never accept some events; they are dead-lettered.

    Without ``event_ids`` the whole batch is refused. With them, only the events of the batch
    whose ``event_id`` is listed are refused, and the sink has delivered every other one.
    ``reasons`` may give each refused event its own reason (kept with its dead letter);
    events without one get the message.
    """

    def __init__(
        self,
        message: str,
        *,
        sink: str | None = None,
        event_ids: Iterable[str] = (),
        reasons: Mapping[str, str] | None = None,
    ) -> None:
        self.reasons = dict(reasons or {})
        self.event_ids = frozenset(event_ids) | frozenset(self.reasons)
        super().__init__(message, sink=sink)


class SinkLoadError(SinkError):
    """Raised when a sink named in config cannot be found, imported or configured."""


class SinkOptionsInvalid(SinkLoadError):
    """Raised when a sink's ``options`` fail its options model; carries both, for messages."""

    def __init__(self, sink: str, validation: Exception, model: type) -> None:
        super().__init__(f"options of sink type {sink!r} are invalid", sink=sink)
        self.validation = validation
        self.model = model


class SpoolError(GatewayError):
    """Raised when the spool database cannot be opened, read or written (disk, schema)."""


class HttpAnswerError(GatewayError):
    """Raised when an HTTPS server's answer cannot be read: not HTTP/1.1, or past a bound."""


class OrderRejected(GatewayError):
    """Raised when an order from a C2 system fails its acceptance checks."""

    def __init__(self, message: str, *, airframe: str | None = None) -> None:
        self.airframe = airframe
        super().__init__(message)


class ScoreInputError(GatewayError, ValueError):
    """Raised when ``fischer-gateway score`` cannot use a file: it names the file and line."""

    def __init__(self, source: str, line: int | None, message: str) -> None:
        self.source = source
        self.line = line
        where = f"{source}:{line}" if line is not None else source
        super().__init__(f"{where}: {message}")


def os_reason(exc: BaseException) -> str:
    """The plain reason of an OS failure: the first ``strerror`` in ``exc``'s cause chain.

    uvloop wraps a failed bind as ``OSError("could not bind to local_addr ...")`` without an
    errno; the real "Address already in use" is only in its ``__cause__``.
    """
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.strerror:
            return seen.strerror
        seen = seen.__cause__ or seen.__context__
    return str(exc)
