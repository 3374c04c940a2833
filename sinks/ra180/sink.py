"""The Ra 180 sink: new hostile tracks to the platoons' radio net, as text and as Swedish voice.

Each ``Track`` worth telling the net becomes one Compact Data Message of at most 127
characters (``sinks.ra180.cdm``), sent to a radio data terminal on a serial port or to a
radio gateway over UDP, within a byte budget per minute: new hostile tracks first, updates
only when the track moved ``update_min_move_m``, repeats suppressed, a newer message of a
track replacing its held one (``sinks/ra180/budget.py``). With ``voice`` set, each new
target is also announced in Swedish by espeak-ng to a WAV file for the radio's audio input
(``sinks/ra180/voice.py``). Everything is in docs/ra180.md.

``send`` only offers tracks to the budget and returns, so the runner counts them delivered
once held: the budget, not the spool, decides what the net hears, and what is held when the
gateway stops is not sent after a restart (a new track is announced again as it is updated).
The sink's lifetime (``run``) transmits: a missing or lost serial device, or a UDP send the
network refuses, is retried with backoff while messages wait, never fatal; ``/status``
shows the radio and voice state and what was held back under the sink's ``detail``.
"""

from __future__ import annotations

import math
import os
import random
import re
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal, Protocol

import anyio
import anyio.abc
import structlog
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from gateway.c2.sink import SinkConfig
from gateway.errors import PermanentSinkError
from gateway.events import Event, EventKind, Track
from gateway.ops.logsetup import RateLimit
from gateway.transports.serial import SerialWriter, is_supported_baud
from gateway.transports.udp_peer import UdpPeer
from sinks.ra180.budget import Budget, Outgoing
from sinks.ra180.cdm import (
    CLASS_ABBREVIATIONS,
    MANDATORY_MAX_CHARS,
    MAX_CDM_CHARS,
    Cdm,
    CdmError,
    CdmPrecision,
    MessageType,
    check_abbreviation,
    check_originator,
    compose,
)
from sinks.ra180.voice import Voice, VoiceSettings

__all__ = [
    "Ra180SerialConfig",
    "Ra180Sink",
    "Ra180SinkConfig",
    "Ra180UdpConfig",
    "Ra180VoiceConfig",
]

log = structlog.get_logger(__name__)

_KINDS = frozenset({EventKind.TRACK})
_STRICT = ConfigDict(frozen=True, extra="forbid")
#: Serial frames end with CR LF, which the budget counts too.
SERIAL_END = b"\r\n"


class Ra180UdpConfig(BaseModel):
    """A radio gateway taking one CDM per datagram (ASCII, no line end)."""

    model_config = _STRICT

    host: str = Field(min_length=1, description="The radio gateway's address or name.")
    port: int = Field(ge=1, le=65535, description="Its UDP port.")


class Ra180SerialConfig(BaseModel):
    """A radio data terminal on a serial port, raw 8N1; each CDM ends with CR LF."""

    model_config = _STRICT

    device: str = Field(min_length=1, description="The serial device, e.g. /dev/ttyUSB0.")
    baud: int = Field(default=9600, description="Line speed (a termios speed: 1200, 9600 ...).")
    write_timeout_s: float = Field(
        default=10.0, gt=0, le=300, description="A write taking longer fails and is retried."
    )

    @field_validator("baud")
    @classmethod
    def _baud(cls, value: int) -> int:
        if not is_supported_baud(value):
            raise ValueError(f"{value} is not a serial line speed here (try 9600 or 19200)")
        return value


class Ra180VoiceConfig(BaseModel):
    """Swedish announcements of new targets, one WAV file each, for the radio's audio input."""

    model_config = _STRICT

    directory: Path = Field(description="Where the WAV files are written (created if missing).")
    program: str = Field(default="espeak-ng", min_length=1, description="The synthesiser.")
    voice: str = Field(default="sv", pattern=r"^[A-Za-z0-9_+/-]{1,40}$", description="Its voice.")
    words_per_minute: int = Field(default=140, ge=80, le=450, description="Speaking rate.")
    timeout_s: float = Field(default=20.0, gt=0, le=300, description="Deadline per rendering.")
    max_files: int = Field(default=200, ge=1, le=100_000, description="WAV files kept at most.")
    max_bytes: int = Field(
        default=50_000_000, ge=100_000, le=10_000_000_000, description="WAV bytes kept at most."
    )
    queue_max: int = Field(default=16, ge=1, le=1000, description="Announcements waiting.")
    announce: Literal["new", "all"] = Field(
        default="new", description="Announce new targets only, or updates too."
    )

    def settings(self) -> VoiceSettings:
        """What the renderer takes."""
        return VoiceSettings(
            self.directory,
            self.program,
            self.voice,
            self.words_per_minute,
            self.timeout_s,
            self.max_files,
            self.max_bytes,
            self.queue_max,
        )


class Ra180SinkConfig(SinkConfig):
    """Options of the ``ra180`` sink (``sinks[].options``)."""

    udp: Ra180UdpConfig | None = Field(default=None, description="Send to a radio gateway.")
    serial: Ra180SerialConfig | None = Field(default=None, description="Or to a data terminal.")
    report: tuple[Literal["hostile", "suspect", "unknown"], ...] = Field(
        default=("hostile",), min_length=1, description="Which track hostilities the net hears."
    )
    mgrs_precision_m: CdmPrecision = Field(default=10, description="Grid references at 10 or 1 m.")
    max_chars: int = Field(
        default=MAX_CDM_CHARS,
        ge=MANDATORY_MAX_CHARS,
        le=MAX_CDM_CHARS,
        description="The longest message; optional fields are dropped to fit.",
    )
    originator: str | None = Field(default=None, description="Call sign sent as FRAN (optional).")
    abbreviations: dict[str, str] = Field(
        default_factory=dict,
        max_length=64,
        description="Class abbreviations replacing or adding to the built-in table.",
    )
    bytes_per_minute: int = Field(
        default=1200, ge=200, le=10_000_000, description="The net's data budget."
    )
    burst_bytes: int = Field(
        default=260, ge=MAX_CDM_CHARS + len(SERIAL_END), description="The budget's bucket size."
    )
    update_min_move_m: float = Field(
        default=100.0, ge=0, le=100_000, description="An update is sent once moved this far."
    )
    min_speed_mps: float = Field(
        default=0.5, ge=0, le=1000, description="Course and speed are sent from this speed up."
    )
    max_tracks: int = Field(
        default=1000, ge=1, le=10_000, description="Tracks remembered and held at most."
    )
    retry_initial_s: float = Field(default=1.0, gt=0, le=60, description="First retry delay.")
    retry_max_s: float = Field(default=30.0, gt=0, le=600, description="Longest retry delay.")
    voice: Ra180VoiceConfig | None = Field(default=None, description="Swedish announcements.")

    @field_validator("originator")
    @classmethod
    def _originator(cls, value: str | None) -> str | None:
        return None if value is None else check_originator(value)

    @field_validator("abbreviations")
    @classmethod
    def _abbreviations(cls, value: dict[str, str]) -> dict[str, str]:
        return {name: check_abbreviation(text) for name, text in value.items()}

    @model_validator(mode="after")
    def _consistent(self) -> Ra180SinkConfig:
        if (self.udp is None) == (self.serial is None):
            raise ValueError("give exactly one of udp or serial")
        if self.bytes_per_minute <= self.burst_bytes:
            raise ValueError(
                f"bytes_per_minute ({self.bytes_per_minute}) must be more than burst_bytes "
                f"({self.burst_bytes})"
            )
        if self.retry_max_s < self.retry_initial_s:
            raise ValueError("retry_max_s must be at least retry_initial_s")
        return self


class _Radio(Protocol):
    """Where frames go: the UDP radio gateway or the serial data terminal."""

    describe: str

    async def send(self, frame: bytes) -> None: ...

    async def aclose(self) -> None: ...


class _UdpRadio:
    # A connected socket: a gateway that is not listening (ICMP port unreachable) is an
    # OSError here, so the message stays held and is sent again, rather than lost unseen.
    def __init__(self, config: Ra180UdpConfig) -> None:
        self._sender = UdpPeer(config.host, config.port)
        self.describe = f"udp://{config.host}:{config.port}"

    async def send(self, frame: bytes) -> None:
        await self._sender.send(frame)

    async def aclose(self) -> None:
        await self._sender.aclose()


class _SerialRadio:
    def __init__(self, config: Ra180SerialConfig) -> None:
        self._port = SerialWriter(
            config.device, config.baud, write_timeout_s=config.write_timeout_s
        )
        self.describe = f"serial://{config.device}?baud={config.baud}"

    async def send(self, frame: bytes) -> None:
        await self._port.write(frame)

    async def aclose(self) -> None:
        self._port.close()


def _is_known_class(name: str) -> bool:
    """True for an object class a track can have (``gateway.fleet.normalise`` names them)."""
    return name in CLASS_ABBREVIATIONS or re.fullmatch(r"class_\d+", name) is not None


def _make_radio(config: Ra180SinkConfig) -> _Radio:
    if config.udp is not None:
        return _UdpRadio(config.udp)
    if config.serial is not None:
        return _SerialRadio(config.serial)
    raise ValueError("give exactly one of udp or serial")  # the model's validator says so too


class Ra180Sink:
    """Tracks to a Ra 180 net: CDMs within a byte budget, and Swedish voice announcements."""

    config_model = Ra180SinkConfig

    def __init__(self, name: str, config: Ra180SinkConfig) -> None:
        self.name = name
        self.config = config
        self.log = log.bind(sink=name)
        self._abbreviations = {**CLASS_ABBREVIATIONS, **config.abbreviations}
        self._radio = _make_radio(config)
        self._frame_end = b"" if config.udp is not None else SERIAL_END
        self.budget = Budget(
            self._encode,
            bytes_per_minute=config.bytes_per_minute,
            burst_bytes=config.burst_bytes,
            min_move_m=config.update_min_move_m,
            max_tracks=config.max_tracks,
            report=frozenset(config.report),
        )
        self.voice = None if config.voice is None else Voice(config.voice.settings(), sink=name)
        self.radio_state = "idle"
        self.radio_reason = ""
        self._wake: anyio.Event | None = None
        self._radio_log = RateLimit(interval_s=30.0)

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Tracks only."""
        return _KINDS

    def _encode(self, track: Track, message_type: MessageType, number: int) -> tuple[Cdm, bytes]:
        cdm = compose(
            track,
            message_type=message_type,
            number=number,
            precision_m=self.config.mgrs_precision_m,
            abbreviations=self._abbreviations,
            originator=self.config.originator,
            min_speed_mps=self.config.min_speed_mps,
        ).fitted(self.config.max_chars)
        frame = " ".join(cdm.fields()).encode("ascii") + self._frame_end
        return cdm, frame

    def environment_warnings(self) -> list[str]:
        """What on this node the sink will wait for or do without (``check-config``)."""
        notes = []
        serial = self.config.serial
        if serial is not None and not os.path.exists(serial.device):
            notes.append(f"{serial.device} does not exist now; messages wait for it")
        unknown = [name for name in self.config.abbreviations if not _is_known_class(name)]
        if unknown:
            known = ", ".join(c for c in CLASS_ABBREVIATIONS if c != "other") + " and other"
            notes.append(
                f"abbreviations for {', '.join(map(repr, unknown))}: no track has such a class "
                f"(the classes are {known}, which stands for any class not listed, or class_N "
                "for a number the fleet does not name), so the entry is never used"
            )
        voice = self.config.voice
        if voice is not None and shutil.which(voice.program) is None:
            notes.append(
                f"{voice.program} not found on PATH: no voice announcements until the Debian "
                "package espeak-ng is installed (the messages still go out)"
            )
        return notes

    async def open(self) -> None:
        """Nothing to connect: the lifetime opens the radio and retries it while it is away."""

    async def send(self, batch: Sequence[Event]) -> None:
        """Offer each track to the budget and wake the transmitter; never waits on the radio.

        ``PermanentSinkError(event_ids=...)`` names tracks no CDM can carry (a polar
        position), after every other track was taken.
        """
        refused: list[str] = []
        for event in batch:
            if not isinstance(event, Track):
                continue
            try:
                self.budget.offer(event)
            except CdmError as exc:
                refused.append(event.event_id)
                if self._radio_log.allow("unencodable"):
                    self.log.warning(
                        "ra180_track_unencodable", track=event.track_id, error=str(exc)
                    )
        if self._wake is not None:
            self._wake.set()
        if refused:
            raise PermanentSinkError(
                f"sink {self.name}: {len(refused)} track(s) cannot be written as a CDM "
                "(no MGRS reference at their position)",
                sink=self.name,
                event_ids=refused,
            )

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Transmit held messages as the budget allows, and render the voice, until cancelled."""
        async with anyio.create_task_group() as tg:
            if self.voice is not None:
                tg.start_soon(self.voice.run)
            task_status.started()
            await self._transmit()

    async def _transmit(self) -> None:
        delay = self.config.retry_initial_s
        while True:
            item = await self._next_due()
            try:
                await self._radio.send(item.frame)
            except OSError as exc:
                await self._radio.aclose()
                reason = f"{self._radio.describe}: {exc.strerror or exc}"
                if self.radio_reason != reason or self._radio_log.allow("down"):
                    self.log.warning("ra180_radio_unavailable", error=reason, held=self.budget.held)
                self.radio_state, self.radio_reason = "waiting for radio", reason
                await anyio.sleep(delay * random.uniform(0.5, 1.0))  # noqa: S311 - jitter
                delay = min(delay * 2, self.config.retry_max_s)
                continue
            delay = self.config.retry_initial_s
            if self.radio_state != "sending":
                self.log.info("ra180_radio_sending", radio=self._radio.describe)
            self.radio_state, self.radio_reason = "sending", ""
            self.budget.sent(item, anyio.current_time())
            announce = self.config.voice is not None and (
                self.config.voice.announce == "all" or item.cdm.type == "MAL"
            )
            if self.voice is not None and announce:
                self.voice.submit(item.cdm)

    async def _next_due(self) -> Outgoing:
        while True:
            now = anyio.current_time()
            item = self.budget.next_due(now)
            if item is not None:
                return item
            wait = self.budget.wait_s(now)
            self._wake = anyio.Event()
            with anyio.move_on_after(math.inf if wait is None else max(wait, 0.001)):
                await self._wake.wait()

    async def aclose(self) -> None:
        """Close the radio; held messages stay held for the next ``open``."""
        self._wake = None
        await self._radio.aclose()

    def counts(self) -> dict[str, int]:
        """Monotonic counts by outcome, for ``fg_sink_outcomes_total{sink, outcome}``."""
        c = self.budget.counts
        counts = {
            "offered": c.offered,
            "sent": c.sent,
            "held_back": c.held_back,
            "suppressed": c.suppressed,
            "superseded": c.superseded,
            "not_reported": c.not_reported,
            "unencodable": c.unencodable,
            "dropped_full": c.dropped_full,
            "dropped_lost": c.dropped_lost,
            "bytes_sent": c.bytes_sent,
        }
        if self.voice is not None:
            v = self.voice.counts
            counts |= {
                "voice_rendered": v.rendered,
                "voice_failed": v.failed,
                "voice_dropped": v.dropped,
                "voice_unavailable": v.unavailable,
            }
        return counts

    def status(self) -> dict[str, Any]:
        """The radio, the budget and the voice, for ``/status`` (the sink's ``detail``)."""
        c = self.budget.counts
        detail: dict[str, Any] = {
            "radio": self._radio.describe,
            "radio_state": self.radio_state,
            "radio_reason": self.radio_reason,
            "held": self.budget.held,
            "held_back": c.held_back,
            "offered": c.offered,
            "sent": c.sent,
            "sent_new": c.sent_new,
            "sent_update": c.sent_update,
            "bytes_sent": c.bytes_sent,
            "suppressed": c.suppressed,
            "superseded": c.superseded,
            "not_reported": c.not_reported,
            "unencodable": c.unencodable,
            "dropped_full": c.dropped_full,
            "dropped_lost": c.dropped_lost,
            "budget_bytes_per_minute": self.config.bytes_per_minute,
            "budget_tokens": round(self.budget.bucket.tokens, 1),
        }
        if self.voice is not None:
            v = self.voice.counts
            detail["voice"] = {
                "state": self.voice.state,
                "reason": self.voice.reason,
                "waiting": self.voice.waiting,
                "rendered": v.rendered,
                "failed": v.failed,
                "dropped": v.dropped,
                "unavailable": v.unavailable,
                "removed": v.removed,
                "last_file": None if self.voice.last_file is None else str(self.voice.last_file),
            }
        return detail
