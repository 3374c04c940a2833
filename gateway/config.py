"""The gateway's configuration: pydantic models of the YAML and the link URI type.

Everything is validated once, at load (``gateway.configfile``), never at the point of use.
Unknown keys are errors, models are frozen, units are in field names. Secrets never live in
the config: options that need one take a path to a file or a systemd credential name.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from ipaddress import ip_address
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import parse_qsl, urlsplit

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
    model_validator,
)

from gateway.domain.energy import EnergyProfile, EwMode
from gateway.domain.hopping import AD9361_MAX_BW_HZ, AD9361_RANGE_HZ, HopPlan, HopPlanError
from gateway.events import LATEST_WINS_KINDS, EventKind

__all__ = [
    "SIGNED_ONLY_MSGIDS",
    "AirframeConfig",
    "Config",
    "DemSourceConfig",
    "Endpoint",
    "GatewayConfig",
    "HealthConfig",
    "HopPlanConfig",
    "LinkConfig",
    "ProcessorEntry",
    "RouteConfig",
    "SigningConfig",
    "SinkEntry",
    "SourceEntry",
    "TerrainConfig",
    "TunnelConfig",
    "parse_endpoint",
]

# allow_inf_nan=False: a duration of .inf would mean "never" (a failover that never comes).
_FROZEN = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)
_ID = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"


@dataclass(frozen=True, slots=True)
class Endpoint:
    """A parsed link URI: ``udp://``, ``tcp://`` or ``serial://``, listening or connecting."""

    scheme: Literal["udp", "tcp", "serial"]
    mode: Literal["listen", "connect"]
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 57600
    text: str = field(default="", compare=False)

    def __str__(self) -> str:
        return self.text


_MODES: dict[str, tuple[str, ...]] = {"udp": ("listen", "connect"), "tcp": ("connect", "listen")}


def parse_endpoint(value: object) -> Endpoint:
    """Parse a link URI; raise ``ValueError`` saying what was expected.

    ``udp://HOST:PORT`` listens (``?mode=connect`` sends to that address), ``tcp://HOST:PORT``
    connects (``?mode=listen`` serves), ``serial:///dev/ttyX?baud=57600`` opens a device.
    """
    if isinstance(value, Endpoint):
        return value
    if not isinstance(value, str):
        raise ValueError(f"expected a link URI string, found {type(value).__name__}")
    parts = urlsplit(value)
    scheme = parts.scheme
    try:
        params = dict(parse_qsl(parts.query, strict_parsing=bool(parts.query)))
    except ValueError as exc:
        raise ValueError(f"expected key=value query parameters, found {parts.query!r}") from exc
    if scheme == "serial":
        device = parts.path
        if parts.netloc or not device.startswith("/"):
            raise ValueError(f"expected serial:///dev/DEVICE, found {value!r}")
        unknown = set(params) - {"baud"}
        if unknown:
            raise ValueError(f"expected only 'baud' as a serial parameter, found {sorted(unknown)}")
        baud_text = params.get("baud", "57600")
        if not (baud_text.isascii() and baud_text.isdigit()) or int(baud_text) not in SERIAL_BAUDS:
            raise ValueError(
                f"expected a standard baud rate ({', '.join(map(str, SERIAL_BAUDS))}), "
                f"found {baud_text!r}"
            )
        return Endpoint("serial", "connect", device=device, baud=int(baud_text), text=value)
    if scheme not in _MODES:
        raise ValueError(f"expected udp://, tcp:// or serial://, found {value!r}")
    unknown = set(params) - {"mode"}
    if unknown:
        raise ValueError(f"expected only 'mode' as a {scheme} parameter, found {sorted(unknown)}")
    mode = params.get("mode", _MODES[scheme][0])
    if mode not in ("listen", "connect"):
        raise ValueError(f"expected mode=listen or mode=connect, found mode={mode!r}")
    try:
        host, port = parts.hostname, parts.port
    except ValueError as exc:
        raise ValueError(
            f"expected {scheme}://HOST:PORT with a port 1-65535, found {value!r}"
        ) from exc
    if not host or port is None or parts.path not in ("", "/"):
        raise ValueError(f"expected {scheme}://HOST:PORT, found {value!r}")
    if not _is_host(host):
        raise ValueError(f"expected an IP address or a host name, found {host!r} in {value!r}")
    if port == 0 and mode == "connect":
        raise ValueError(f"expected a port to connect to (1-65535), found {value!r}")
    return Endpoint(scheme, mode, host=host, port=port, text=value)  # type: ignore[arg-type]


#: The rates a Linux serial port can be set to (termios B-constants).
SERIAL_BAUDS = (
    50, 75, 110, 134, 150, 200, 300, 600, 1200, 1800, 2400, 4800, 9600, 19200, 38400, 57600,
    115200, 230400, 460800, 500000, 576000, 921600, 1000000, 1152000, 1500000, 2000000, 2500000,
    3000000, 3500000, 4000000,
)  # fmt: skip
_HOST_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")


def _is_host(host: str) -> bool:
    """An IPv4 or IPv6 literal, or a DNS name (RFC 1123) that is not a malformed IPv4."""
    try:
        ip_address(host)
    except ValueError:
        pass
    else:
        return True
    labels = host.rstrip(".").split(".")
    if all(label.isascii() and label.isdigit() for label in labels):
        return False  # looks like IPv4 but did not parse: 192.0.2.300
    return len(host) <= 253 and all(_HOST_LABEL.fullmatch(label) for label in labels)


EndpointField = Annotated[
    Endpoint,
    BeforeValidator(parse_endpoint),
    PlainSerializer(str, return_type=str),
    WithJsonSchema(
        {
            "type": "string",
            "pattern": r"^(udp|tcp|serial)://",
            "description": "udp://HOST:PORT[?mode=listen|connect], tcp://HOST:PORT"
            "[?mode=connect|listen], serial:///dev/DEVICE[?baud=N]",
        }
    ),
]


#: Messages a signed link never accepts unsigned (gateway/fleet/hopdialect.py has their ids):
#: an unsigned hop answer would make the gateway believe a schedule the airframe never took.
SIGNED_ONLY_MSGIDS: dict[int, str] = {
    61003: "FISCHER_HOP_SCHEDULE_ACK",
    61004: "FISCHER_HOP_EVENT",
}


class SigningConfig(BaseModel):
    """MAVLink 2 signing for an airframe whose autopilot cannot run the tunnel."""

    model_config = _FROZEN

    key_file: Path = Field(description="32 raw bytes or 64 hex digits; mode 0600 or stricter.")
    require_signed: bool = Field(
        default=True, description="false accepts unsigned frames too: for the lab only."
    )
    accept_unsigned_msgids: tuple[int, ...] = Field(
        default=(), description="Unsigned message ids accepted anyway, e.g. 109 RADIO_STATUS."
    )

    @field_validator("accept_unsigned_msgids")
    @classmethod
    def _hop_messages_signed(cls, msgids: tuple[int, ...]) -> tuple[int, ...]:
        for msgid in msgids:
            name = SIGNED_ONLY_MSGIDS.get(msgid)
            if name is not None:
                raise ValueError(
                    f"{msgid} ({name}) cannot be accepted unsigned: anyone on the link could "
                    "forge it and steer the hop schedule"
                )
        return msgids


class TunnelConfig(BaseModel):
    """The AES-256-GCM tunnel's key source and time windows."""

    model_config = _FROZEN

    master_key_file: Path | None = Field(
        default=None, description="32+ raw bytes or hex; must not be group/world-readable."
    )
    master_key_credential: str | None = Field(
        default=None,
        pattern=_ID,
        description="Name of a systemd credential (LoadCredential=) holding the master key.",
    )
    grace_s: float = Field(
        default=600.0, ge=0, le=86400, description="Yesterday's key accepted after 00:00."
    )
    skew_s: float = Field(default=120.0, ge=0, le=3600, description="Tomorrow's key before 00:00.")
    freshness_s: float = Field(default=30.0, gt=0, le=3600, description="Max frame age.")


class LinkConfig(BaseModel):
    """One transport to an airframe."""

    model_config = _FROZEN

    uri: EndpointField
    security: Literal["tunnel", "signed", "unsecured"] = Field(
        description="tunnel: AES-256-GCM frames; signed: MAVLink 2 signing; unsecured must "
        "be chosen explicitly and is shown as such on /status."
    )
    name: str | None = Field(default=None, pattern=_ID, description="Defaults to the URI.")
    priority: int = Field(default=0, ge=0, le=100, description="Lower is preferred.")
    max_frame_bytes: int = Field(
        default=2048, ge=64, le=65535, description="Largest datagram or tunnel frame accepted."
    )
    reconnect_initial_s: float = Field(
        default=0.5, gt=0, le=3600, description="First wait before reconnecting or reopening."
    )
    reconnect_max_s: float = Field(
        default=30.0, gt=0, le=3600, description="Longest wait between reconnect attempts."
    )
    max_connections: int = Field(
        default=16, ge=1, le=4096, description="tcp ?mode=listen only: connections held at once."
    )
    idle_timeout_s: float = Field(
        default=30.0,
        gt=0,
        le=86400,
        description="tcp ?mode=listen only: a connection silent this long is closed.",
    )
    allow_non_loopback: bool = Field(
        default=False,
        description="An unsecured link may listen beyond loopback only if this says so.",
    )

    @property
    def label(self) -> str:
        """The name shown in metrics and logs."""
        return self.name or str(self.uri)


_MAX_DWELL_US = 4_000_000.0  # FISCHER_HOP_SCHEDULE carries nanoseconds in a uint32


class HopPlanConfig(BaseModel):
    """The AD9361 hop plan the gateway uploads to an airframe (docs/hopping.md).

    Validated at load like the rest of the config: every frequency within the AD9361's
    70 MHz to 6 GHz, the bandwidth within its 56 MHz, at most 8 fastlock slots, and a dwell
    that beats a reactive jammer reacting in ``jammer_reaction_us`` (the dwell must be
    shorter). The same checks run again right before each upload.
    """

    model_config = _FROZEN

    frequencies_mhz: tuple[
        Annotated[float, Field(ge=AD9361_RANGE_HZ[0] / 1e6, le=AD9361_RANGE_HZ[1] / 1e6)], ...
    ] = Field(
        min_length=1,
        max_length=8,
        description="Centre frequency of each fastlock slot in hop order, 70 to 6000 MHz; "
        "1 to 8 of them.",
    )
    bandwidth_mhz: float = Field(
        ge=1e-6,  # 1 Hz: the message carries whole hertz
        le=AD9361_MAX_BW_HZ / 1e6,
        description="RF bandwidth on every channel, MHz.",
    )
    jammer_reaction_us: float = Field(
        default=20.0,
        gt=0,
        le=_MAX_DWELL_US,
        description="Reaction time of the reactive (follower) jammer the plan must beat.",
    )
    dwell_us: float = Field(
        ge=0.001,
        le=_MAX_DWELL_US,
        description="Time on each channel, µs; must be shorter than jammer_reaction_us.",
    )
    settle_us: float = Field(
        default=0.0,
        ge=0,
        le=_MAX_DWELL_US,
        description="PLL settling per hop the plan allows, µs (0: hidden by a second synthesizer).",
    )
    ack_timeout_s: float = Field(
        default=1.0, gt=0, le=60, description="First wait for the airframe's answer."
    )
    retry_max_s: float = Field(
        default=30.0,
        gt=0,
        le=3600,
        description="Longest wait between two uploads (the backoff doubles up to it).",
    )

    @field_validator("dwell_us")
    @classmethod
    def _beats_jammer(cls, dwell_us: float, info: ValidationInfo) -> float:
        reaction_us = info.data.get("jammer_reaction_us")
        if reaction_us is not None and not dwell_us < reaction_us:
            raise ValueError(
                f"a dwell of {dwell_us:g} µs does not beat a reactive jammer reacting in "
                f"{reaction_us:g} µs (jammer_reaction_us): the dwell must be shorter"
            )
        return dwell_us

    @model_validator(mode="after")
    def _flyable(self) -> HopPlanConfig:
        try:
            self.plan()
        except HopPlanError as exc:
            raise ValueError(str(exc)) from exc
        return self

    def plan(self) -> HopPlan:
        """The domain's ``HopPlan`` of this config (Hz and seconds); ``HopPlanError`` if the
        AD9361 cannot run it."""
        return HopPlan(
            frequencies_hz=tuple(round(f * 1e6) * 1.0 for f in self.frequencies_mhz),
            bandwidth_hz=round(self.bandwidth_mhz * 1e6) * 1.0,
            dwell_s=self.dwell_us * 1e-6,
            settle_s=self.settle_us * 1e-6,
        )

    @property
    def jammer_reaction_s(self) -> float:
        """``jammer_reaction_us`` in seconds."""
        return self.jammer_reaction_us * 1e-6


class PassthroughConfig(BaseModel):
    """A local MAVLink endpoint for a ground station, and what it may send to the airframe.

    ``uplink`` has no default, as a link's ``security`` has none: ``none`` (telemetry out
    only), ``signed`` (the ground station signs with its own key, ``key_file``) or ``open``
    (any local process). Whatever the mode, the command policy of
    ``gateway/fleet/uplinkpolicy.py`` decides what reaches the airframe.
    """

    model_config = _FROZEN

    uri: EndpointField = Field(description="udp://HOST:PORT[?mode=listen|connect], on loopback.")
    uplink: Literal["none", "signed", "open"] = Field(
        description="none: telemetry out only; signed: only frames signed with key_file; "
        "open: any local process (warned at start, shown on /status)."
    )
    key_file: Path | None = Field(
        default=None,
        description="With uplink: signed, the ground station's own MAVLink 2 signing key "
        "(32 raw bytes or 64 hex digits, mode 0600), never the airframe's.",
    )
    param_set_allow: tuple[str, ...] = Field(
        default=(),
        max_length=256,
        description="Parameter names (fnmatch patterns, e.g. MPC_XY_CRUISE) a ground station "
        "may set; none by default, and never one that maps outputs (SERVO*, RELAY*, ...).",
    )
    allow_non_loopback: bool = Field(
        default=False,
        description="The endpoint may bind beyond loopback only if this says so.",
    )

    @field_validator("uri")
    @classmethod
    def _udp_only(cls, uri: Endpoint) -> Endpoint:
        if uri.scheme != "udp":
            raise ValueError(f"expected a udp:// endpoint for the passthrough, found {uri}")
        return uri

    @model_validator(mode="after")
    def _key_matches_mode(self) -> PassthroughConfig:
        if self.uplink == "signed" and self.key_file is None:
            raise ValueError(
                "uplink: signed needs key_file: the ground station's MAVLink 2 signing key, "
                "SHA-256 of its passphrase in hex (docs/security.md#the-passthrough)"
            )
        if self.uplink != "signed" and self.key_file is not None:
            raise ValueError(f"key_file is used only with uplink: signed (uplink is {self.uplink})")
        return self


class AirframeConfig(BaseModel):
    """One airframe of the fleet."""

    model_config = _FROZEN

    id: str = Field(pattern=_ID, description="The airframe's name in events, e.g. F26E-001.")
    sysid: int = Field(ge=1, le=255, description="MAVLink system id.")
    links: tuple[LinkConfig, ...] = Field(
        min_length=1, description="Its transports; the only links that may speak for it."
    )
    link_timeout_s: float = Field(
        default=3.0, gt=0, le=3600, description="A link not heard this long is down (failover)."
    )
    failback_hold_s: float = Field(
        default=3.0,
        ge=0,
        le=3600,
        description="A preferred link must be up this long to take over again.",
    )
    dedup_window_s: float = Field(
        default=0.5,
        gt=0,
        lt=1.0,
        description="A frame seen again on another link within this window is delivered once.",
    )
    signing: SigningConfig | None = Field(
        default=None, description="MAVLink 2 signing key; required by a signed link."
    )
    energy: EnergyProfile = Field(
        default=EnergyProfile(), description="Battery and power figures for predicted endurance."
    )
    ew_mode: EwMode = Field(
        default=EwMode.ACTIVE, description="EW mode assumed for predicted endurance."
    )
    passthrough: PassthroughConfig | None = Field(
        default=None,
        description="A local MAVLink endpoint for QGroundControl, MAVProxy or MAVSDK, with "
        "its uplink stated (docs/security.md#the-passthrough).",
    )
    hop_plan: HopPlanConfig | None = Field(
        default=None,
        description="An AD9361 hop plan uploaded to the airframe once it is linked "
        "(FISCHER_HOP_SCHEDULE; docs/hopping.md).",
    )
    autopilot: Literal["px4", "ardupilot", "mavlink"] | None = Field(
        default=None,
        description="Whose modes start its missions and send it home: px4 (AUTO.MISSION, "
        "AUTO.RTL), ardupilot (AUTO, RTL by number: ArduPlane, or ArduCopter when its "
        "HEARTBEAT says multirotor) or mavlink (MISSION_START, NAV_RETURN_TO_LAUNCH). "
        "Unset: the autopilot its HEARTBEAT names, else the orders processor's mode_commands.",
    )
    mode_commands: Literal["px4", "mavlink"] | None = Field(
        default=None, description="The older name of autopilot (px4 or mavlink)."
    )

    @model_validator(mode="before")
    @classmethod
    def _mode_commands_alias(cls, data: object) -> object:
        if isinstance(data, dict) and data.get("mode_commands") is not None:
            given = data.get("autopilot")
            if given is not None and given != data["mode_commands"]:
                raise ValueError(
                    f"autopilot: {given} and mode_commands: {data['mode_commands']} disagree;"
                    " mode_commands is the older name of autopilot: give one"
                )
            data = {**data, "autopilot": data["mode_commands"]}
        return data

    @field_validator("passthrough", mode="before")
    @classmethod
    def _uplink_stated(cls, value: object) -> object:
        if isinstance(value, str):
            raise ValueError(
                "the passthrough must state what a ground station may send: write "
                f"passthrough: {{uri: {value!r}, uplink: none|signed|open}} (none: telemetry "
                "out only; signed: with the ground station's key_file; open: any local "
                "process; docs/security.md#the-passthrough)"
            )
        return value


class DemSourceConfig(BaseModel):
    """A directory of DEM tiles the operator supplies; nothing is downloaded."""

    model_config = _FROZEN

    name: str = Field(pattern=_ID, description="e.g. lantmateriet_2m, srtm_30m")
    kind: Literal["hgt", "geotiff"] = Field(
        description="hgt: SRTM tiles (nothing extra); geotiff: needs the [terrain] extra."
    )
    directory: Path = Field(description="Where the tiles are.")
    sigma_m: float = Field(gt=0, description="The DEM's 1σ vertical error.")


class TerrainConfig(BaseModel):
    """Ground elevation sources, tried in order, for height above ground on telemetry."""

    model_config = _FROZEN

    sources: tuple[DemSourceConfig, ...] = Field(
        default=(), description="Tried in order; the first with data for a point answers."
    )
    baro_sigma_m: float = Field(default=0.5, gt=0, description="Barometric altitude 1σ.")


class SinkEntry(BaseModel):
    """One configured output sink: its type (an entry point name) and delivery settings."""

    model_config = _FROZEN

    name: str = Field(pattern=_ID, description="Named by routes, metrics and /status.")
    type: str = Field(
        pattern=r"^[a-z][a-z0-9_]*$",
        description="An installed sink type (entry point fischer_gateway.sinks): jsonl, cot ...",
    )
    options: dict[str, Any] = Field(
        default_factory=dict, description="The sink type's own options (see its schema)."
    )
    queue_max: int = Field(default=10_000, ge=1, description="Durable events held in memory.")
    batch_max: int = Field(
        default=100, ge=1, le=10_000, description="Events handed to one send call at most."
    )
    send_timeout_s: float = Field(
        default=5.0, gt=0, le=3600, description="Deadline of one open or send call."
    )
    retry_initial_s: float = Field(
        default=0.5, gt=0, le=3600, description="First backoff after a failed send."
    )
    retry_max_s: float = Field(
        default=30.0, gt=0, le=86400, description="Longest backoff between attempts."
    )


class StaleRule(BaseModel):
    """What the spool does with a durable event of one kind that waited too long (an outage)."""

    model_config = _FROZEN

    after_s: float = Field(gt=0, le=30 * 86400, description="Age in the spool that makes it stale.")
    action: Literal["deliver_late", "expire"] = Field(
        description="deliver_late: sent with late_by_s set; expire: dead-lettered as expired."
    )


def _default_stale() -> dict[EventKind, StaleRule]:
    return {
        EventKind.DETECTION: StaleRule(after_s=3600.0, action="deliver_late"),
        EventKind.TRACK: StaleRule(after_s=3600.0, action="deliver_late"),
        # A counter-UAS cue minutes old points at where the target was: expire it, the
        # tracker cues the battery again if the track is still alive.
        EventKind.HANDOFF: StaleRule(after_s=60.0, action="expire"),
        EventKind.ORDER: StaleRule(after_s=3600.0, action="deliver_late"),
        EventKind.ORDER_STATUS: StaleRule(after_s=3600.0, action="deliver_late"),
    }


class SpoolConfig(BaseModel):
    """The SQLite spool that holds durable events until each sink confirms them."""

    model_config = _FROZEN

    path: Path | None = Field(
        default=None,
        description="The spool database file (WAL mode). Unset: in memory, lost on restart.",
    )
    sync: Literal["normal", "full"] = Field(
        default="normal",
        description="normal: survives kill -9 and crashes of the process, not a power cut; "
        "full: an fsync per commit, survives a power cut, costs the disk's sync latency.",
    )
    max_bytes: int = Field(
        default=1 << 30,
        ge=1 << 20,
        description="Size cap; new durable events are refused above it.",
    )
    warn_pct: float = Field(
        default=80.0, gt=0, le=100, description="Log loudly when the spool is this full."
    )
    stale: dict[EventKind, StaleRule] = Field(
        default_factory=_default_stale,
        description="Per durable kind: when an event counts as stale, and whether it is then "
        "delivered marked late or expired into the dead letters.",
    )
    dedup_window_s: float = Field(
        default=3600.0,
        gt=0,
        le=30 * 86400,
        description="How long detection ids are remembered to drop an airframe's re-sends.",
    )
    dead_letters_max: int = Field(
        default=100_000, ge=1, description="Dead letters kept; the oldest go first."
    )

    @field_validator("stale")
    @classmethod
    def _durable_only(cls, stale: dict[EventKind, StaleRule]) -> dict[EventKind, StaleRule]:
        latest = sorted(k.value for k in stale if k in LATEST_WINS_KINDS)
        if latest:
            raise ValueError(f"latest-wins kinds are never spooled: {latest}")
        return {**_default_stale(), **stale}


class SourceEntry(BaseModel):
    """One configured source: ``name``, ``type`` (an entry point name) and its own options.

    The options sit beside ``name`` and ``type`` (``{name: atak, type: cot, uri: ...}``); the
    source type's model validates them (``check-config`` and ``run`` do so at load).
    """

    model_config = ConfigDict(frozen=True, extra="allow")

    name: str = Field(default="cot", pattern=_ID, description="Named in metrics and /status.")
    type: str = Field(
        default="cot",
        pattern=r"^[a-z][a-z0-9_]*$",
        description="An installed source type (entry point fischer_gateway.sources).",
    )

    @property
    def options(self) -> dict[str, Any]:
        """Everything beside ``name`` and ``type``: the source type's options."""
        return dict(self.model_extra or {})


class ProcessorEntry(BaseModel):
    """One configured processor: its type (an entry point name) and its inbox."""

    model_config = _FROZEN

    name: str = Field(pattern=_ID, description="Named in metrics, logs and /status.")
    type: str = Field(
        pattern=r"^[a-z][a-z0-9_]*$",
        description="An installed processor type (entry point fischer_gateway.processors).",
    )
    options: dict[str, Any] = Field(
        default_factory=dict, description="The processor type's own options (see its schema)."
    )
    queue_max: int = Field(
        default=10_000, ge=1, le=1_000_000, description="Events waiting for it before drops."
    )


class RouteConfig(BaseModel):
    """Which events go to which sinks. An omitted filter matches everything."""

    model_config = _FROZEN

    sinks: tuple[str, ...] = Field(min_length=1, description="Names of configured sinks.")
    kinds: tuple[EventKind, ...] | None = Field(
        default=None, description="Event kinds routed (telemetry, detection ...); all if omitted."
    )
    airframes: tuple[str, ...] | None = Field(
        default=None, description="Airframe ids routed; all if omitted."
    )
    classes: tuple[str, ...] | None = Field(
        default=None, description="Detection/track classes routed; all if omitted."
    )
    max_rate_hz: float | None = Field(
        default=None,
        gt=0,
        description="Per airframe, for latest-wins kinds only; durable kinds are never thinned.",
    )


class HealthConfig(BaseModel):
    """The HTTP health and metrics endpoint."""

    model_config = _FROZEN

    enabled: bool = Field(default=True, description="false: no health endpoint at all.")
    host: str = Field(
        default="127.0.0.1",
        description="Address to bind; beyond loopback needs allow_non_loopback.",
    )
    port: int = Field(default=8765, ge=0, le=65535, description="0 picks a free port.")
    allow_non_loopback: bool = Field(
        default=False,
        description="/status and /metrics describe the fleet: binding beyond loopback must be "
        "stated here.",
    )
    max_connections: int = Field(
        default=32, ge=1, le=1024, description="Connections held at once; more are closed."
    )


class GatewayConfig(BaseModel):
    """Settings of the daemon itself."""

    model_config = _FROZEN

    node_id: str = Field(
        default="fischer-gateway", pattern=_ID, description="This node's name in logs and /status."
    )
    shutdown_deadline_s: float = Field(
        default=5.0,
        gt=0,
        le=300,
        description="Drain and close within this on SIGTERM; keep TimeoutStopSec above it.",
    )
    log_level: Literal["debug", "info", "warning", "error"] = Field(
        default="info", description="Lowest level logged."
    )


class Config(BaseModel):
    """The whole configuration file."""

    model_config = _FROZEN

    gateway: GatewayConfig = Field(default=GatewayConfig(), description="The daemon itself.")
    health: HealthConfig = Field(
        default=HealthConfig(), description="/healthz, /readyz, /metrics and /status."
    )
    tunnel: TunnelConfig = Field(
        default=TunnelConfig(), description="The master key and time windows of tunnel links."
    )
    terrain: TerrainConfig = Field(
        default=TerrainConfig(), description="DEM sources for height above ground."
    )
    spool: SpoolConfig = Field(
        default=SpoolConfig(), description="Where durable events wait for the sinks."
    )
    sources: tuple[SourceEntry, ...] = Field(
        default=(), description="Inputs beyond the airframes: CoT from ATAK/WinTAK (blue force)."
    )
    processors: tuple[ProcessorEntry, ...] = Field(
        default=(), description="Components that derive events from events (fusion ...)."
    )
    airframes: tuple[AirframeConfig, ...] = Field(default=(), description="The fleet.")
    sinks: tuple[SinkEntry, ...] = Field(default=(), description="Where events go.")
    routes: tuple[RouteConfig, ...] = Field(
        default=(), description="Which events go to which sinks."
    )
