"""The typed events every stage of the gateway speaks.

Events are frozen pydantic models with UTC-aware times and SI units in field names. They are
validated once, where they are made (``normalise``), and never mutated afterwards. A sink
receives events, never MAVLink messages.

Each event has a ``kind`` discriminator and a stable ``event_id``: a receiver that gets the
same event twice (delivery is at-least-once for durable kinds) can de-duplicate on it.
Durable kinds have ``late_by_s``: None, unless the spool delivers the event after its kind's
stale threshold, when it says how many seconds the event waited.
"""

from __future__ import annotations

import hashlib
import re
import secrets
from collections.abc import Callable, Mapping
from enum import StrEnum
from functools import cache
from typing import Annotated, Any, Literal, TypeVar

from pydantic import (
    AwareDatetime,
    BaseModel,
    ConfigDict,
    Field,
    JsonValue,
    TypeAdapter,
    field_validator,
    model_validator,
)

__all__ = [
    "ALT_MAX_M",
    "ALT_MIN_M",
    "BOOT_ID",
    "DURABLE_KINDS",
    "EXTENSION_DATA_MAX_BYTES",
    "EXTENSION_DATA_MAX_DEPTH",
    "EXTENSION_TYPE_MAX",
    "EXTENSION_TYPE_PATTERN",
    "LATEST_WINS_KINDS",
    "MAX_DECLARED_EXTENSIONS",
    "MAX_TRACK_NODES",
    "Attitude",
    "BlueForce",
    "BlueSourceCount",
    "Deconfliction",
    "Detection",
    "EffectorOption",
    "Event",
    "EventKind",
    "Extension",
    "FiveLineOrder",
    "Handoff",
    "HopEvent",
    "HopReason",
    "LinkState",
    "OrderArea",
    "OrderPriority",
    "OrderState",
    "OrderStatus",
    "OrderTask",
    "Position",
    "Provenance",
    "Sensor",
    "Telemetry",
    "Track",
    "Velocity",
    "VideoFrameMetadata",
    "checked",
    "checked_fields",
    "checked_from",
    "checked_template",
    "declared_extensions",
    "event_adapter",
    "event_id",
    "latest_key",
    "plausible_alt",
]

BOOT_ID = secrets.token_hex(4)
"""This process's identity in event ids that count from its start (one per process)."""


_M = TypeVar("_M", bound=BaseModel)
_set = object.__setattr__


@cache
def _template(cls: type[BaseModel]) -> dict[str, Any]:
    # Every field in declaration order (the order pydantic serialises a dict in), defaults
    # filled in; the required ones hold None until the caller's values replace them.
    return {
        name: None if info.is_required() else info.get_default(call_default_factory=True)
        for name, info in cls.model_fields.items()
    }


def checked(cls: type[_M], **values: Any) -> _M:
    """An instance of ``cls`` from values its builder has already checked: no validation.

    For the hot paths that check every value themselves (``fleet/normalise.py``): pydantic's
    validation there is a second check, and ``model_construct`` is slower still (it walks
    the fields in Python). Give every required field and only values of the declared
    types; the instance is the one the validating constructor would build from them. Defaults
    must be immutable (a default factory's value is shared between instances).
    """
    return checked_from(cls, values)


def checked_from(cls: type[_M], values: dict[str, Any]) -> _M:
    """``checked`` from a dict of the values (the hot path builds one dict, not keywords)."""
    fields = _template(cls).copy()
    fields.update(values)
    return checked_fields(cls, fields, set(values))


def checked_template(cls: type[BaseModel]) -> dict[str, Any]:
    """Every field of ``cls`` in declaration order, defaults filled in (None where required).

    A builder that makes many instances keeps this, and gives ``checked_fields`` a copy of
    it with its values written in.
    """
    return _template(cls).copy()


def checked_fields(cls: type[_M], fields: dict[str, Any], given: set[str]) -> _M:
    """``checked`` from every field's value and the names of those given (not defaulted).

    ``fields`` is a copy of ``checked_template(cls)`` with the given values written in (the
    instance keeps it as its ``__dict__``); the same rules as ``checked`` hold.
    """
    instance = cls.__new__(cls)
    _set(instance, "__dict__", fields)
    _set(instance, "__pydantic_fields_set__", given)
    _set(instance, "__pydantic_extra__", None)
    _set(instance, "__pydantic_private__", None)
    return instance


def event_id(*parts: object) -> str:
    """The stable id of an event from its parts: ``event_id("F26E-001", "det", 7, ts)``.

    Receivers de-duplicate by it, so the same event always gets the same id; events numbered
    by a counter of this process include ``BOOT_ID`` so a restart never repeats an id.
    """
    return "-".join(str(part) for part in parts)


class EventKind(StrEnum):
    """The kinds of event, and so the keys of routes and sink declarations."""

    TELEMETRY = "telemetry"
    LINK_STATE = "link_state"
    DETECTION = "detection"
    TRACK = "track"
    BLUE_FORCE = "blue_force"
    HANDOFF = "handoff"
    ORDER = "order"
    HOP = "hop"
    VIDEO_FRAME_METADATA = "video_frame_metadata"
    ORDER_STATUS = "order_status"
    EXTENSION = "extension"


#: Kinds where only the newest event per key matters: a slow sink gets fresh data, not a backlog.
LATEST_WINS_KINDS: frozenset[EventKind] = frozenset(
    {
        EventKind.TELEMETRY,
        EventKind.LINK_STATE,
        EventKind.BLUE_FORCE,
        EventKind.HOP,
        # Up to 30 a second per airframe, each describing one video frame: a late one is
        # worthless to a video client, so a slow sink gets the newest, never a backlog.
        EventKind.VIDEO_FRAME_METADATA,
    }
)
#: Kinds that must never be dropped silently: delivered at least once, in order per sink.
DURABLE_KINDS: frozenset[EventKind] = frozenset(EventKind) - LATEST_WINS_KINDS

_FROZEN = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

#: A track names at most this many other nodes whose detections contributed to it.
MAX_TRACK_NODES = 16
#: A gateway node's name in ``origin_node`` (the ``nats`` subject token of the node).
_NODE_NAME = r"^[A-Za-z0-9_-]{1,32}$"


#: The altitudes (metres, MSL or HAE) a position may hold: below the lowest dry land and the
#: deepest a sensor reports from, to the edge of space. Outside is a corrupt or hostile value
#: (a float's 3e38 from a link), never a place: sources refuse it, the normaliser drops it.
ALT_MIN_M = -12_000.0
ALT_MAX_M = 100_000.0


def plausible_alt(value: float) -> float | None:
    """``value`` if it is a finite altitude within ``ALT_MIN_M``..``ALT_MAX_M``, else None."""
    return value if ALT_MIN_M <= value <= ALT_MAX_M else None  # NaN compares False


class Position(BaseModel):
    """A WGS 84 position. Altitudes are metres; any of them may be unknown."""

    model_config = _FROZEN

    lat_deg: float = Field(ge=-90.0, le=90.0)
    """Latitude, degrees north (WGS 84)."""
    lon_deg: float = Field(ge=-180.0, le=180.0)
    """Longitude, degrees east (WGS 84)."""
    alt_msl_m: float | None = Field(default=None, ge=ALT_MIN_M, le=ALT_MAX_M)
    """Altitude above mean sea level, metres; None when unknown."""
    alt_hae_m: float | None = Field(default=None, ge=ALT_MIN_M, le=ALT_MAX_M)
    """Height above the WGS 84 ellipsoid, metres; None when unknown (telemetry sets it once GPS
    has given the geoid separation)."""
    alt_rel_home_m: float | None = Field(default=None, ge=-ALT_MAX_M, le=ALT_MAX_M)
    """Altitude above the airframe's home, metres; None when unknown."""


class Attitude(BaseModel):
    """Euler angles in radians (aircraft body frame, NED)."""

    model_config = _FROZEN

    roll_rad: float
    """Roll, radians, positive right wing down."""
    pitch_rad: float
    """Pitch, radians, positive nose up."""
    yaw_rad: float
    """Yaw, radians from north, positive clockwise."""


class Velocity(BaseModel):
    """Velocity over ground in the local NED frame, metres per second."""

    model_config = _FROZEN

    north_mps: float
    """Towards north, m/s."""
    east_mps: float
    """Towards east, m/s."""
    down_mps: float
    """Downwards, m/s (negative when climbing; 0 in a track, which is 2-D)."""


class Sensor(StrEnum):
    """The sensor behind a detection."""

    EO = "eo"
    IR = "ir"
    RF = "rf"


class Telemetry(BaseModel):
    """The latest known state of one airframe, merged from its MAVLink messages.

    ``position`` is None until the airframe has reported one with a fix; a consumer that
    needs a position must skip such events, never plot them at 0,0.
    """

    model_config = _FROZEN

    kind: Literal[EventKind.TELEMETRY] = EventKind.TELEMETRY
    event_id: str
    """Unique per snapshot: airframe, ``tel``, ``BOOT_ID`` and a counter of this process."""
    airframe: str
    """The configured id of the airframe (``airframes[].id``)."""
    time: AwareDatetime
    """When the gateway made this snapshot (its clock, UTC)."""
    position: Position | None = None
    """From GLOBAL_POSITION_INT; None until a fix (a report at 0,0 clears it)."""
    alt_agl_m: float | None = None
    """Height above the terrain below, metres, where a terrain model covers the point; else None."""
    agl_sigma_m: float | None = None
    """One-sigma uncertainty of ``alt_agl_m``, metres (barometer and terrain model combined)."""
    attitude: Attitude | None = None
    """From ATTITUDE; None until one with finite angles arrives."""
    velocity: Velocity | None = None
    """Over ground in NED, from GLOBAL_POSITION_INT."""
    heading_deg: float | None = None
    """Heading, degrees from north (GLOBAL_POSITION_INT ``hdg``); None until the autopilot
    reports one."""
    groundspeed_mps: float | None = None
    """Ground speed, m/s, from VFR_HUD."""
    airspeed_mps: float | None = None
    """Airspeed, m/s, from VFR_HUD."""
    climb_mps: float | None = None
    """Climb rate, m/s, from VFR_HUD."""
    gps_fix_type: int | None = None
    """GPS_RAW_INT ``fix_type`` (MAVLink GPS_FIX_TYPE: 0-1 no fix, 2 2-D, 3 3-D, 4+ DGPS/RTK)."""
    satellites_visible: int | None = None
    """Satellites the GPS sees; None when the autopilot does not know (255)."""
    h_acc_m: float | None = None
    """GPS horizontal accuracy, metres (MAVLink 2 ``h_acc``); None when not reported."""
    battery_pct: float | None = None
    """Battery remaining, percent (SYS_STATUS or BATTERY_STATUS); None when unknown."""
    battery_voltage_v: float | None = None
    """Battery voltage, volts (SYS_STATUS); None when unknown."""
    battery_current_a: float | None = None
    """Battery current, amperes (SYS_STATUS or BATTERY_STATUS); None when unknown."""
    battery_consumed_wh: float | None = None
    """Energy drawn so far, watt-hours (BATTERY_STATUS); None when unknown."""
    battery_time_remaining_s: float | None = None
    """The autopilot's own estimate of battery time left, seconds (BATTERY_STATUS); None when not
    given."""
    endurance_remaining_min: float | None = Field(default=None, ge=0)
    """The gateway's prediction of flight time left, minutes, from the battery and the airframe's
    energy profile (worst case: no solar, current EW mode)."""
    ew_mode: str | None = None
    """The electronic-warfare mode the endurance prediction assumes (``permissive``, ``active``,
    ``heavy``); None when the gateway does not predict endurance."""
    mav_type: int | None = None
    """HEARTBEAT ``type`` (MAVLink MAV_TYPE) of the autopilot."""
    autopilot: int | None = None
    """HEARTBEAT ``autopilot`` (MAVLink MAV_AUTOPILOT)."""
    is_armed: bool | None = None
    """Whether the autopilot reports itself armed (HEARTBEAT ``base_mode``)."""
    custom_mode: int | None = None
    """HEARTBEAT ``custom_mode``: the flight mode in the autopilot's own numbering."""
    system_status: int | None = None
    """HEARTBEAT ``system_status`` (MAVLink MAV_STATE)."""
    active_link: str | None = None
    """The label of the link the gateway uses for this airframe now; None when none is up."""
    origin_node: str | None = Field(default=None, pattern=_NODE_NAME)
    """The gateway node this event came from when another node sent it (the ``nats`` source);
    None for this node's own. A node never sends on an event that carries one."""


class LinkState(BaseModel):
    """A change in the health of one link of one airframe."""

    model_config = _FROZEN

    kind: Literal[EventKind.LINK_STATE] = EventKind.LINK_STATE
    event_id: str
    """Unique per change: airframe, ``link``, ``BOOT_ID`` and a counter of this process."""
    airframe: str
    """The configured id of the airframe."""
    time: AwareDatetime
    """When the gateway saw the change."""
    link: str
    """The link's label: its configured ``name``, else its URI."""
    is_up: bool
    """Heard within ``link_timeout_s``."""
    is_active: bool
    """The link the gateway uses for this airframe now (the preferred one that is up)."""
    loss_pct: float = Field(ge=0.0, le=100.0)
    """Autopilot frames lost to sequence gaps on this link, percent of those expected, since the
    gateway started."""
    last_heard: AwareDatetime | None = None
    """When an authenticated frame last arrived on this link; None if never."""
    reason: str
    """What caused the change, in words: ``heard on <link>``, ``<link> not heard for <timeout>
    s``, ``hold elapsed``."""


class Detection(BaseModel):
    """One object detected by one sensor of one airframe."""

    model_config = _FROZEN

    kind: Literal[EventKind.DETECTION] = EventKind.DETECTION
    event_id: str
    """Airframe, ``det``, the airframe's detection id and its ``time_usec``: the same report re-
    sent has the same id."""
    airframe: str
    """The configured id of the airframe that saw it."""
    time: AwareDatetime
    """When it was observed: the airframe's time when within a day behind or a minute ahead of
    the gateway's, else when received."""
    sensor: Sensor
    """The sensor that saw it."""
    object_class: str
    """What it is, a class name of the dialect (``tank``, ``armour``, ``infantry_platoon``,
    ``uav``, ``loitering_munition``; ``class_<n>`` for an unknown class id)."""
    subtype: str = ""
    """A finer type the airframe gave, as text; empty when none."""
    confidence: float = Field(ge=0.0, le=1.0)
    """The airframe's confidence in ``object_class``, 0..1."""
    position: Position
    """Where the object is (latitude, longitude; altitude above MSL when given)."""
    sigma_h_m: float = Field(ge=0.0)
    """One-sigma horizontal position error, metres (ingest refuses one above 10 km)."""
    frame_size: int | None = Field(default=None, ge=1, le=255)
    """How many detections the airframe says its sensor frame (same airframe, sensor and time)
    holds, this one included; None when it did not say. Fusion takes a frame as soon as it holds
    that many rather than waiting ``frame_wait_s`` for more."""
    origin_node: str | None = Field(default=None, pattern=_NODE_NAME)
    """The gateway node this event came from when another node sent it (the ``nats`` source);
    None for this node's own. A node never sends on an event that carries one."""
    late_by_s: float | None = Field(default=None, ge=0.0)
    """Set when the spool delivers the event after its kind's stale threshold: how many seconds
    it waited."""


class Track(BaseModel):
    """A fused track built from one or more detections (``tracking``).

    One ``track_id`` for the track's whole life; each create, update and loss is its own
    event (``status``). A track found to be a second track of another's object ends as
    ``merged``, naming the surviving track in ``merged_into``; each event of one track has a
    strictly newer ``time`` than the one before it. ``confidence`` is the Dempster-Shafer
    belief in ``object_class``; ``class_conflict`` the conflict K of the latest combination
    (0: the sensors agreed).
    ``detection_ids`` holds the newest contributing detections (at most 32).
    """

    model_config = _FROZEN

    kind: Literal[EventKind.TRACK] = EventKind.TRACK
    event_id: str
    """``<track_id>-<n>``, n counting the track's events."""
    track_id: str
    """The track's id for its whole life."""
    time: AwareDatetime
    """The newest detection's time, or the moment of the loss or merge; strictly newer than the
    track's previous event."""
    status: Literal["created", "updated", "lost", "merged"] = "updated"
    """``created``, ``updated``, ``lost`` (no detection for too long) or ``merged`` (see
    ``merged_into``)."""
    merged_into: str | None = None
    """For ``merged``: the id of the track this one was folded into (it lives on)."""
    object_class: str
    """The class with the strongest belief after combining the detections' classes."""
    subtype: str = ""
    """A subtype a detection of ``object_class`` gave; empty when none."""
    confidence: float = Field(ge=0.0, le=1.0)
    """The combined (Dempster-Shafer) belief in ``object_class``, 0..1."""
    class_conflict: float = Field(default=0.0, ge=0.0, le=1.0)
    """The conflict K of the latest combination of class evidence: 0 when the sensors agreed."""
    position: Position
    """The filter's estimated position."""
    cep50_m: float = Field(ge=0.0)
    """Circular error probable, metres: the radius holding the object with 50 % probability."""
    cep90_m: float = Field(ge=0.0)
    """The radius holding the object with 90 % probability, metres."""
    velocity: Velocity | None = None
    """Over ground (``down_mps`` 0); None until the filter's velocity is good enough to report."""
    speed_mps: float | None = Field(default=None, ge=0.0)
    """Ground speed, m/s; None whenever ``velocity`` is."""
    course_deg: float | None = Field(default=None, ge=0.0, lt=360.0)
    """Course over ground, degrees from north; None whenever ``velocity`` is."""
    detection_ids: tuple[str, ...] = ()
    """The ``event_id``s of the newest contributing detections, at most 32."""
    detection_count: int = Field(default=0, ge=0)
    """How many detections contributed over the track's life."""
    airframes: tuple[str, ...] = ()
    """The airframes whose detections contributed, sorted."""
    origin_nodes: tuple[Annotated[str, Field(pattern=_NODE_NAME)], ...] = Field(
        default=(), max_length=MAX_TRACK_NODES
    )
    """The other gateway nodes whose detections contributed (their ``origin_node``), sorted, at
    most 16 (the first 16 heard); empty when every detection was this node's own."""
    sensors: tuple[Sensor, ...] = ()
    """The sensors whose detections contributed, sorted."""
    first_seen: AwareDatetime
    """The time of the track's first detection."""
    last_seen: AwareDatetime
    """The time of its newest detection."""
    hostility: Literal["hostile", "suspect", "unknown", "neutral", "friend"] = "unknown"
    """Affiliation: the tracker gives ``hostile`` to the classes configured hostile and
    ``suspect`` to the rest."""
    sidc: str | None = None
    """The MIL-STD-2525C symbol code for its class and hostility; None when the symbol table has
    none (a sink then picks a generic one)."""
    late_by_s: float | None = Field(default=None, ge=0.0)
    """Set when the spool delivers the event after its kind's stale threshold: how many seconds
    it waited."""


class Provenance(StrEnum):
    """How far the sender of a friendly report (and its text) was checked.

    - ``configured``: fixed in the gateway's own config (the ``counter_uas`` processor's
      ``blue_forces``): the operator wrote it; no peer can send or move it.
    - ``authenticated``: received over TLS from a peer whose client certificate chains to the
      CA the source names (NFFI ``tls://``). The *transport* is authenticated: the peer holds a
      key that CA vouched for. What it relays (another system's callsign) is still its word.
    - ``address_only``: received over plain TCP from an address on the source's allow-list
      (NFFI ``tcp://``). An address check, not authentication: any process on an allowed host,
      or anyone able to use its address, can send.
    - ``unauthenticated``: anyone who can reach the port (CoT over UDP, multicast or TCP). The
      default for a report that does not say.
    """

    CONFIGURED = "configured"
    AUTHENTICATED = "authenticated"
    ADDRESS_ONLY = "address_only"
    UNAUTHENTICATED = "unauthenticated"


class BlueForce(BaseModel):
    """A friendly unit's reported position (from CoT, NFFI ...), used for deconfliction."""

    model_config = _FROZEN

    kind: Literal[EventKind.BLUE_FORCE] = EventKind.BLUE_FORCE
    event_id: str
    """From the source's kind, the unit's uid and (for a report) its time: the same report
    received twice has one id."""
    uid: str
    """The unit's identity as its reporter gives it (CoT uid, NFFI unit id, or configured); the
    key a newer report replaces an older one under."""
    time: AwareDatetime
    """When the report says the unit was there (for a unit fixed in config: when its processor
    started)."""
    callsign: str = ""
    """The unit's name as reported, made safe (``peertext.safe_text``); empty when none. Its
    reporter's word: see ``provenance``."""
    position: Position
    """Where the unit is."""
    source: str
    """The kind of source: ``cot``, ``nffi``, or ``config:<processor>`` for units fixed in
    config."""
    course_deg: float | None = Field(default=None, ge=0.0, lt=360.0)
    """Course over ground, degrees from north, when the report gave one."""
    speed_mps: float | None = Field(default=None, ge=0.0)
    """Speed over ground, m/s, when the report gave one."""
    sidc: str | None = Field(default=None, pattern=r"^[A-Z0-9*-]{15}$")
    """The unit's 15-character letter SIDC (APP-6A / 2525B/C) when the report gave one."""
    source_name: str = ""
    """The configured name of the source (or processor) that produced the report."""
    provenance: Provenance = Provenance.UNAUTHENTICATED
    """How far its sender was checked (``Provenance``); a report that
    does not say (an archive from before provenance existed) is unauthenticated."""


class EffectorOption(BaseModel):
    """One effector the table offers for a cued track, and whether friendly units allow it."""

    model_config = _FROZEN

    effector: str
    """The effector's name in the effector table (``TRACKFIRE_30MM`` ...)."""
    deconfliction_clear: bool
    """No current friendly unit within this effector's danger-close radius of the track (its
    CEP90 taken into account)."""
    danger_close_m: float = Field(ge=0.0)
    """This effector's danger-close radius, metres."""


class BlueSourceCount(BaseModel):
    """How many current friendly units one source gave deconfliction, and how far it is trusted."""

    model_config = _FROZEN

    source: str
    """The source's name, made safe."""
    provenance: Provenance
    """How far that source's senders are checked."""
    units: int = Field(ge=0)
    """Current friendly units from it that the check saw."""


class Deconfliction(BaseModel):
    """The blue-force check of a cued track: the nearest current friendly unit, if any.

    ``clear`` is True only when that unit is beyond the danger-close radius of every effector
    offered and the blue-force picture is complete. ``blue_picture_complete`` is False when
    no friendly position is current at all (nothing known is not "clear") or the gateway had
    to drop friendly reports for room lately; ``clear`` is then always False.
    ``blue_units_considered`` says how many units the check saw, ``blue_sources`` how many of
    them came from each source, with what provenance.

    The nearest unit's uid and callsign are peer text made safe (``peertext.safe_text``);
    ``nearest_blue_callsign_provenance`` says in words what the callsign is ("unauthenticated
    CoT callsign"), ``nearest_blue_source`` and ``nearest_blue_provenance`` which source
    reported the unit and how far its sender was checked. Whatever shows the callsign shows
    its provenance with it.
    """

    model_config = _FROZEN

    clear: bool
    """True only when the nearest friendly unit is beyond every offered effector's danger-close
    radius and the picture is complete."""
    nearest_blue_uid: str | None = None
    """The nearest current friendly unit's uid, made safe; None when none is known."""
    nearest_blue_callsign: str | None = None
    """Its callsign, made safe; show it with ``nearest_blue_callsign_provenance``."""
    nearest_blue_m: float | None = Field(default=None, ge=0.0)
    """Geodesic distance from the track to that unit, metres."""
    blue_units_considered: int = Field(ge=0)
    """How many current friendly units the check saw."""
    blue_picture_complete: bool = True
    """False when no friendly position is current at all or friendly reports were dropped for
    room lately."""
    nearest_blue_callsign_provenance: str | None = None
    """What the callsign is, in words (``unauthenticated CoT callsign``)."""
    nearest_blue_source: str | None = None
    """The source that reported the nearest unit."""
    nearest_blue_provenance: Provenance | None = None
    """How far that unit's sender was checked."""
    blue_sources: tuple[BlueSourceCount, ...] = ()
    """How many of the units considered came from each source, with its provenance."""


class Handoff(BaseModel):
    """A counter-UAS cue: a fused track handed to one GUTE II battery with a recommendation.

    A cue, never an order: ``operator_authorisation_required`` is always True and there is no
    field that could command an effector. ``recommended_effector`` is None whenever the
    deconfliction is not clear; ``options`` still lists each effector with its own result so
    the battery's operator sees why.

    ``handoff_id`` names the cue of one track to one battery for the track's life. When its
    deconfliction or recommendation changes (a friendly unit comes within danger close, say)
    the cue is sent again as the next ``revision``. Each revision is its own delivery:
    ``event_id`` (the idempotency key) is ``handoff_id`` for revision 0 and
    ``<handoff_id>-r<revision>`` after it.

    ``status`` says what the battery should do with the cue: ``active`` (it stands),
    ``superseded`` (its track merged into another that has its own cue, ``superseded_by``;
    drop this one) or ``withdrawn`` (its track was lost: the node no longer tracks the
    object; drop this one). ``note`` says in words why a revision was sent.
    """

    model_config = _FROZEN

    kind: Literal[EventKind.HANDOFF] = EventKind.HANDOFF
    event_id: str
    """``handoff_id`` for revision 0, ``<handoff_id>-r<revision>`` after it: the idempotency key
    of each delivery."""
    handoff_id: str
    """The cue of one track to one battery, for the track's life."""
    revision: int = Field(default=0, ge=0)
    """0 for the first cue; one more for each revision sent after it."""
    status: Literal["active", "superseded", "withdrawn"] = "active"
    """``active`` (the cue stands), ``superseded`` (drop it: see ``superseded_by``) or
    ``withdrawn``."""
    superseded_by: str | None = None
    """For ``superseded``: the ``handoff_id`` of the cue that replaces this one."""
    note: str = ""
    """Why this revision was sent, in words; empty when nothing needs saying."""
    time: AwareDatetime
    """The cued track event's time."""
    battery: str
    """The configured id of the GUTE II battery cued."""
    battery_position: Position
    """Where the battery is (from config)."""
    track: Track
    """The fused track cued, whole."""
    range_m: float = Field(ge=0.0)
    """Geodesic distance from the battery to the track, metres."""
    bearing_deg: float = Field(ge=0.0, lt=360.0)
    """Bearing from the battery to the track, degrees from north."""
    recommended_effector: str | None = None
    """The first offered effector when the deconfliction is clear and the cue active; else None."""
    options: tuple[EffectorOption, ...] = ()
    """Each effector of the battery the table offers for this class and range, with its own
    deconfliction result."""
    deconfliction: Deconfliction
    """The blue-force check against the nearest friendly unit."""
    operator_authorisation_required: Literal[True] = True
    """Always True: a cue for a human operator, never a command."""
    origin_node: str | None = Field(default=None, pattern=r"^[A-Za-z0-9_-]{1,32}$")
    """The gateway node this cue came from when another node sent it (the ``nats`` source);
    None for this node's own. Still only a cue: a node never sends on an event that carries
    one, and nothing on the receiving node turns it into a command."""
    late_by_s: float | None = Field(default=None, ge=0.0)
    """Set when the spool delivers the event after its kind's stale threshold: how many seconds
    it waited."""


class OrderTask(StrEnum):
    """Line 1 of a five-line order: reconnaissance tasking only, nothing that arms or releases."""

    RECON_AREA = "recon_area"
    OBSERVE_POINT = "observe_point"
    TRACK_TARGET = "track_target"
    RETURN_TO_BASE = "return_to_base"


class OrderPriority(StrEnum):
    """Line 4's precedence, highest first."""

    FLASH = "flash"
    IMMEDIATE = "immediate"
    PRIORITY = "priority"
    ROUTINE = "routine"


class OrderArea(BaseModel):
    """Line 2 of a five-line order: a point, or an area as a closed polygon of 3..64 corners.

    ``mgrs`` keeps the grid reference as the issuer wrote it (the point is its decoded
    position); None when the issuer gave latitude and longitude.
    """

    model_config = _FROZEN

    point: Position | None = None
    """Line 2 as one point; None when it is an area."""
    polygon: tuple[Position, ...] = Field(default=(), max_length=64)
    """Line 2 as an area: its corners, 3 to 64; empty when it is a point."""
    mgrs: str | None = Field(default=None, max_length=32)
    """The MGRS reference as the issuer wrote it; ``point`` is its decoded position."""

    @model_validator(mode="after")
    def _one_shape(self) -> OrderArea:
        if (self.point is None) == (not self.polygon):
            raise ValueError("give a point or a polygon of at least 3 corners, not both")
        if self.polygon and len(self.polygon) < 3:
            raise ValueError("an area needs at least 3 corners")
        return self


class FiveLineOrder(BaseModel):
    """A reconnaissance order from a C2 system (SLB, SWECCIS) or a local operator.

    The five lines: 1 ``task``; 2 ``location``; 3 the time window ``not_before`` ..
    ``not_after``; 4 ``target`` and ``priority``; 5 ``reporting`` and ``control_measures``.
    ``order_id`` is the issuer's id; ``event_id`` is ``<system>-order-<order_id>`` (``slb``,
    ``sweccis``: the kind of source, not its configured name) so the same order received twice,
    by any source of that system, is one event; ``source`` is the configured source's name.
    ``airframe`` is the airframe the issuer tasked, or None
    for "any suitable". Taking it in does not accept it: the orders processor checks and
    answers it.
    """

    model_config = _FROZEN

    kind: Literal[EventKind.ORDER] = EventKind.ORDER
    event_id: str
    """``<system>-order-<order_id>`` (``slb``, ``sweccis``, ``local``): one event however many
    sources of that system received it."""
    order_id: str = Field(min_length=1, max_length=128)
    """The issuer's id of the order."""
    source: str = Field(min_length=1, max_length=64)
    """The configured name of the source that took it in; its statuses are answered there."""
    issuer: str | None = Field(default=None, max_length=128)
    """Who issued it, as the C2 system names them; None when not given."""
    time: AwareDatetime
    """When it was issued (as the issuer says)."""
    airframe: str | None = Field(default=None, max_length=64)
    """The airframe tasked; None for any suitable one."""
    task: OrderTask
    """Line 1: what to do."""
    location: OrderArea
    """Line 2: where."""
    not_before: AwareDatetime | None = None
    """Line 3: the earliest start; None for now."""
    not_after: AwareDatetime | None = None
    """Line 3: the end of the window; None for open-ended."""
    target: str | None = Field(default=None, max_length=256)
    """Line 4: the target, in words."""
    track_id: str | None = Field(default=None, max_length=128)
    """For ``track_target``: the fused track to fly to (its newest position replaces
    ``location``)."""
    priority: OrderPriority = OrderPriority.ROUTINE
    """Line 4: the precedence."""
    reporting: str | None = Field(default=None, max_length=512)
    """Line 5: reporting instructions, in words."""
    control_measures: tuple[Annotated[str, Field(max_length=256)], ...] = Field(
        default=(), max_length=16
    )
    """Line 5: control measures, in words (at most 16)."""
    late_by_s: float | None = Field(default=None, ge=0.0)
    """Set when the spool delivers the event after its kind's stale threshold: how many seconds
    it waited."""

    @model_validator(mode="after")
    def _window(self) -> FiveLineOrder:
        if self.not_before and self.not_after and self.not_after < self.not_before:
            raise ValueError("not_after is before not_before")
        return self

    def content_digest(self) -> str:
        """A digest of what the issuer ordered (not when it was issued, who took it in, nor
        when it was spooled): the same ``order_id`` with another digest is a changed order,
        a conflict."""
        content = self.model_dump_json(exclude={"event_id", "source", "time", "late_by_s"})
        return hashlib.sha256(content.encode()).hexdigest()


class HopReason(StrEnum):
    """Why an airframe's radio hopped (FISCHER_HOP_REASON)."""

    SCHEDULED = "scheduled"
    JAMMED = "jammed"
    INTERFERENCE = "interference"


class HopEvent(BaseModel):
    """One hop of an airframe's frequency-hopping radio, as the airframe reported it.

    Latest wins per airframe and ``reason``: the event says which channel the radio is on now
    and why it last left one, so a slow sink gets the newest, and a jam-triggered hop is never
    replaced by a routine one. Counts are never lost to that: ``hop_count`` is the airframe's
    running count of hops on ``schedule_id``, and the gateway's metrics count every report.
    ``is_gateway_schedule`` is True when ``schedule_id`` is the schedule the gateway uploaded
    and the airframe acknowledged. Powers are None when the airframe did not measure them.
    """

    model_config = _FROZEN

    kind: Literal[EventKind.HOP] = EventKind.HOP
    event_id: str
    """Airframe, ``hop``, the schedule id (hex), ``hop_count`` and the airframe's ``time_usec``."""
    airframe: str
    """The configured id of the airframe."""
    time: AwareDatetime
    """When the hop happened (the airframe's time when plausible, else when received)."""
    schedule_id: int = Field(ge=0, lt=2**32)
    """The hop schedule the radio is on."""
    is_gateway_schedule: bool = False
    """``schedule_id`` is the schedule the gateway uploaded and the airframe acknowledged."""
    slot: int = Field(ge=0, le=7)
    """The AD9361 fast-lock profile slot, 0..7."""
    frequency_hz: float = Field(ge=70e6, le=6e9)
    """The channel the radio is on now, Hz (the AD9361's 70 MHz to 6 GHz)."""
    reason: HopReason
    """Why it hopped."""
    hop_count: int = Field(ge=0, lt=2**32)
    """The airframe's running count of hops on ``schedule_id``."""
    rssi_dbm: float | None = Field(default=None, ge=-128.0, le=126.0)
    """Received signal strength on the new channel, dBm; None when not measured."""
    interference_dbm: float | None = Field(default=None, ge=-128.0, le=126.0)
    """Interference on the channel it left, dBm; None when not measured."""


class VideoFrameMetadata(BaseModel):
    """What one airframe's camera sees now: the sensor, its pointing and the frame centre.

    Built from CAMERA_FOV_STATUS and GIMBAL_DEVICE_ATTITUDE_STATUS with the airframe's
    telemetry (``gateway.fleet.video``), for STANAG 4609 video clients (the ``klv`` sink).
    Angles are degrees. ``sensor_azimuth_deg`` (0..360, clockwise), ``sensor_elevation_deg``
    (±180, negative looks down) and ``sensor_roll_deg`` are relative to the platform's body
    axes, as MISB ST 0601 wants them. ``frame_centre`` is where the optical axis meets the
    ground: from the camera (``frame_centre_source`` "camera"), or computed from the pointing
    and the terrain ("computed"); None with ``is_off_earth`` when the axis misses the ground
    (above the horizon), None alone when nothing is known. ``slant_range_m`` is from the
    sensor to the frame centre and ``target_width_m`` the width of the ground the frame
    spans there.
    """

    model_config = _FROZEN

    kind: Literal[EventKind.VIDEO_FRAME_METADATA] = EventKind.VIDEO_FRAME_METADATA
    event_id: str
    """Airframe, ``vfm``, ``BOOT_ID`` and a counter of this process."""
    airframe: str
    """The configured id of the airframe."""
    time: AwareDatetime
    """When the gateway built it."""
    sensor_position: Position
    """Where the camera is: from CAMERA_FOV_STATUS, else the airframe's position."""
    heading_deg: float | None = Field(default=None, ge=0.0, lt=360.0)
    """The platform's heading, degrees from north."""
    pitch_deg: float | None = Field(default=None, ge=-90.0, le=90.0)
    """The platform's pitch, degrees, positive nose up."""
    roll_deg: float | None = Field(default=None, ge=-180.0, le=180.0)
    """The platform's roll, degrees, positive right wing down."""
    airspeed_mps: float | None = None
    """The platform's airspeed, m/s (telemetry)."""
    groundspeed_mps: float | None = None
    """The platform's ground speed, m/s (telemetry)."""
    alt_agl_m: float | None = None
    """The sensor's height above the ground below (terrain model, else home altitude), metres."""
    hfov_deg: float | None = Field(default=None, gt=0.0, le=180.0)
    """Horizontal field of view, degrees (CAMERA_FOV_STATUS)."""
    vfov_deg: float | None = Field(default=None, gt=0.0, le=180.0)
    """Vertical field of view, degrees."""
    sensor_azimuth_deg: float | None = Field(default=None, ge=0.0, lt=360.0)
    """Where the sensor points relative to the platform's nose, degrees clockwise."""
    sensor_elevation_deg: float | None = Field(default=None, ge=-180.0, le=180.0)
    """Sensor elevation relative to the platform, degrees; negative looks down."""
    sensor_roll_deg: float | None = Field(default=None, ge=0.0, lt=360.0)
    """Sensor roll relative to the platform, degrees."""
    frame_centre: Position | None = None
    """Where the optical axis meets the ground; None when off earth or unknown."""
    frame_centre_source: Literal["camera", "computed"] | None = None
    """``camera`` (the camera reported it) or ``computed`` (from pointing and terrain)."""
    is_off_earth: bool = False
    """The optical axis misses the ground (above the horizon)."""
    slant_range_m: float | None = Field(default=None, ge=0.0)
    """From the sensor to the frame centre, metres."""
    target_width_m: float | None = Field(default=None, ge=0.0)
    """The width of the ground the frame spans at the frame centre, metres."""
    image_source: str = Field(default="EO", max_length=32)
    """The sensor's name as MISB ST 0601 tag 11 (image source sensor) carries it; ``EO`` unless
    set."""


class OrderState(StrEnum):
    """Where an order stands: taken in, then accepted or rejected, then executed."""

    RECEIVED = "received"
    WAITING = "waiting"
    """Not yet heard: the airframe has no link (or no position) yet; checked again as it is
    heard, until the order's window ends (then ``rejected`` naming the check)."""
    ACCEPTED = "accepted"
    REJECTED = "rejected"
    CONFLICT = "conflict"
    """The order id was already taken with other content: the changed order is not taken."""
    EXECUTING = "executing"
    COMPLETED = "completed"
    FAILED = "failed"


class OrderStatus(BaseModel):
    """The orders processor's answer to one ``FiveLineOrder``, one event per state reached.

    ``order_event_id`` is the order's ``event_id``; ``order_id`` and ``source`` are copied
    from it so the source that took the order in can answer its issuer. ``event_id`` is
    ``<order_event_id>-<status>``: each state is reported once per order (a ``conflict``
    adds the changed order's digest: one per changed content). ``check`` names what decided a
    waiting, rejection, conflict or failure (``airframe``, ``link``, ``endurance``,
    ``geofence``, ``terrain``, ``area``, ``window``, ``command``, ``mission``, ``order_id``,
    ``track``) and ``reason`` gives its numbers.
    """

    model_config = _FROZEN

    kind: Literal[EventKind.ORDER_STATUS] = EventKind.ORDER_STATUS
    event_id: str
    """``<order_event_id>-<status>``: each state is reported once per order."""
    order_event_id: str
    """The ``event_id`` of the order answered."""
    order_id: str = Field(min_length=1, max_length=128)
    """The issuer's id of the order (copied from it)."""
    source: str = Field(min_length=1, max_length=64)
    """The configured name of the source that took the order in (copied from it)."""
    airframe: str | None = Field(default=None, max_length=64)
    """The airframe the order went to; None when none was chosen."""
    time: AwareDatetime
    """When the orders processor reached this state."""
    status: OrderState
    """The state reached."""
    check: str | None = Field(default=None, max_length=32)
    """What decided a waiting, rejection, conflict or failure (``airframe``, ``link``,
    ``endurance``, ``geofence``, ``terrain``, ``area``, ``window``, ``command``, ``mission``,
    ``order_id``, ``track``)."""
    reason: str | None = Field(default=None, max_length=512)
    """The check's finding with its numbers, in words."""
    mission_items: int | None = Field(default=None, ge=0)
    """How many mission items the order uploaded (from ``accepted`` on); None otherwise."""
    current_item: int | None = Field(default=None, ge=0)
    """For ``completed``: the last mission item, reached and flown to."""
    seq: int | None = Field(default=None, ge=1)
    """The order's status sequence: 1 for its first status, then 2, 3, ... Statuses reach
    the issuer at least once (those owed are sent again after a restart): a receiver drops
    one whose ``order_event_id`` and ``seq`` it already has."""
    origin_node: str | None = Field(default=None, pattern=r"^[A-Za-z0-9_-]{1,32}$")
    """The gateway node this status came from when another node sent it (the ``nats``
    source); None for this node's own. A node never sends on an event that carries one, and
    never answers an issuer of its own with another node's status."""
    late_by_s: float | None = Field(default=None, ge=0.0)
    """Set when the spool delivers the event after its kind's stale threshold: how many seconds
    it waited."""


#: What an extension type is named: two or more dot-separated lowercase parts, the first the
#: publisher's namespace (``acme.weather``, ``acme.radar.sweep``).
EXTENSION_TYPE_PATTERN = r"^[a-z][a-z0-9_]{0,31}(\.[a-z][a-z0-9_]{0,31})+$"
#: The longest extension type name.
EXTENSION_TYPE_MAX = 64
#: ``Extension.data`` may take at most this many bytes as compact JSON ...
EXTENSION_DATA_MAX_BYTES = 16 * 1024
#: ... and nest objects and arrays at most this deep (the object itself is depth 1).
EXTENSION_DATA_MAX_DEPTH = 8


_DATA: TypeAdapter[dict[str, JsonValue]] = TypeAdapter(dict[str, JsonValue])


def _depth(value: JsonValue) -> int:
    if isinstance(value, dict):
        return 1 + max((_depth(v) for v in value.values()), default=0)
    if isinstance(value, list):
        return 1 + max((_depth(v) for v in value), default=0)
    return 0


class Extension(BaseModel):
    """An event of a kind a third-party processor declares: its own ``type`` and ``data``.

    The core knows it only as this envelope: ``type`` names what ``data`` holds
    (``acme.weather``) and a processor may publish only the types it declares in its
    ``extension_events`` (a mapping of type name to the pydantic model of ``data``). The
    gateway checks ``data`` against that model before the event goes on the bus; an
    undeclared type or invalid data is refused and counted under the publishing processor's
    name. Durable: delivered at least once, in order, to every sink whose ``kinds`` include
    ``extension`` (``jsonl`` and ``console`` do; the C2 sinks do not).
    """

    model_config = _FROZEN

    kind: Literal[EventKind.EXTENSION] = EventKind.EXTENSION
    event_id: str = Field(
        min_length=1,
        max_length=256,
        description="The stable id receivers de-duplicate on; the publisher makes it (from "
        "its own input, or with ``BOOT_ID`` for a counter of this process).",
    )
    type: str = Field(
        max_length=EXTENSION_TYPE_MAX,
        pattern=EXTENSION_TYPE_PATTERN,
        description="What ``data`` holds: a namespaced name the publisher declared "
        "(``acme.weather``).",
    )
    time: AwareDatetime = Field(description="When what ``data`` describes happened or held.")
    publisher: str = Field(
        default="",
        max_length=64,
        description="The configured name of the processor that published it; the gateway "
        "sets it as it accepts the event.",
    )
    airframe: str | None = Field(
        default=None,
        max_length=64,
        description="The airframe it concerns, if any; routes' ``airframes`` filter on it.",
    )
    data: dict[str, JsonValue] = Field(
        default_factory=dict,
        description="A JSON object valid against the model the publisher declared for "
        f"``type``; at most {EXTENSION_DATA_MAX_BYTES} bytes as JSON and "
        f"{EXTENSION_DATA_MAX_DEPTH} levels deep.",
    )
    late_by_s: float | None = Field(
        default=None,
        ge=0.0,
        description="Set when the spool delivers the event after a stale rule configured "
        "for ``extension``: how many seconds it waited.",
    )

    @field_validator("data")
    @classmethod
    def _bounded(cls, data: dict[str, JsonValue]) -> dict[str, JsonValue]:
        depth = _depth(data)
        if depth > EXTENSION_DATA_MAX_DEPTH:
            raise ValueError(f"nests {depth} levels deep; at most {EXTENSION_DATA_MAX_DEPTH}")
        size = len(_DATA.dump_json(data))
        if size > EXTENSION_DATA_MAX_BYTES:
            raise ValueError(f"takes {size} bytes as JSON; at most {EXTENSION_DATA_MAX_BYTES}")
        return data


_TYPE = re.compile(EXTENSION_TYPE_PATTERN)
#: A processor may declare at most this many extension types.
MAX_DECLARED_EXTENSIONS = 64


def declared_extensions(factory: object) -> dict[str, type[BaseModel]]:
    """The ``extension_events`` a processor class (or instance) declares; {} when none.

    Raises ``ValueError`` saying what is wrong with a declaration that is not a mapping of
    valid type names to pydantic models.
    """
    declared = getattr(factory, "extension_events", None)
    if declared is None:
        return {}
    if not isinstance(declared, Mapping):
        raise ValueError(
            f"extension_events must map type names to pydantic models, got {declared!r}"
        )
    if len(declared) > MAX_DECLARED_EXTENSIONS:
        raise ValueError(
            f"extension_events declares {len(declared)} types; at most {MAX_DECLARED_EXTENSIONS}"
        )
    types: dict[str, type[BaseModel]] = {}
    for name, model in declared.items():
        if not (
            isinstance(name, str) and len(name) <= EXTENSION_TYPE_MAX and _TYPE.fullmatch(name)
        ):
            raise ValueError(
                f"extension_events: {name!r} is not a type name: dot-separated lowercase "
                f"parts, a namespace first ('acme.weather'), at most {EXTENSION_TYPE_MAX} "
                "characters"
            )
        if not (isinstance(model, type) and issubclass(model, BaseModel)):
            raise ValueError(f"extension_events[{name!r}] must be a pydantic model, got {model!r}")
        types[name] = model
    return types


Event = Annotated[
    Telemetry
    | LinkState
    | Detection
    | Track
    | BlueForce
    | Handoff
    | FiveLineOrder
    | OrderStatus
    | HopEvent
    | VideoFrameMetadata
    | Extension,
    Field(discriminator="kind"),
]

#: Validates or parses any event from Python objects or JSON (``event_adapter.validate_json``).
event_adapter: TypeAdapter[Event] = TypeAdapter(Event)


_SLOTS: dict[type, Callable[[Any], str]] = {
    Telemetry: lambda e: "telemetry\x00" + e.airframe,
    LinkState: lambda e: f"link_state\x00{e.airframe}\x00{e.link}",
    BlueForce: lambda e: "blue_force\x00" + e.uid,
    HopEvent: lambda e: f"hop\x00{e.airframe}\x00{e.reason.value}",
    VideoFrameMetadata: lambda e: "video_frame_metadata\x00" + e.airframe,
}


def latest_key(event: Event) -> str | None:
    """The slot a latest-wins event replaces its predecessor in; None for durable kinds."""
    slot = _SLOTS.get(type(event))
    return None if slot is None else slot(event)
