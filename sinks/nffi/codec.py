"""NFFI 1.3 (STANAG 5527) track messages: own airframes and friendly reports, both ways.

``encode_message`` writes one ``NFFIMessage`` (namespace ``urn:nato:fft:protocols:nffi13``)
holding a ``track`` per event: ``Telemetry`` of an own airframe (only with a position) and
``BlueForce`` (a relayed friendly report). Every value is made to fit the 1.3 schema's
types: identifiers keep only the characters it permits (others become ``-``) and its lengths,
``dateTime`` is ``YYYYMMDDhhmmss`` UTC, altitude is metres above mean sea level, bearing is in
[0, 360) and **speed is km/h** (our events carry m/s). docs/nffi.md has the mapping table.

``parse_message`` reads one document from the network (hostile input): defusedxml with DTDs,
entities and external references refused, a size bound, at most ``MAX_TRACKS`` tracks. A
document that is not an ``NFFIMessage`` raises ``NffiError`` (a ``FrameError``) with a
``problem`` code; a track inside a good document that lacks what a position report needs is
skipped and its problem returned beside the tracks that were read.
"""

from __future__ import annotations

import math
import re
import unicodedata
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import lru_cache
from xml.sax.saxutils import escape, quoteattr

from defusedxml import DefusedXmlException
from defusedxml.ElementTree import fromstring

from gateway.domain.symbols import own_symbol
from gateway.errors import FrameError
from gateway.events import BlueForce, Event, Position, Telemetry

__all__ = [
    "KMH_PER_MPS",
    "MAX_MESSAGE_BYTES",
    "MAX_TRACKS",
    "NAMESPACE",
    "NffiError",
    "NffiOptions",
    "NffiTrack",
    "ParsedMessage",
    "encode_message",
    "encode_track",
    "fit_identifier",
    "nffi_time",
    "parse_message",
    "track_uid",
    "tracks_of",
]

NAMESPACE = "urn:nato:fft:protocols:nffi13"
#: 1 m/s is 3.6 km/h: NFFI's speed unit is km/h, ours m/s.
KMH_PER_MPS = 3.6
#: The largest document ``parse_message`` reads (a source's bound may be lower).
MAX_MESSAGE_BYTES = 1 << 20
#: Tracks read from one document; the rest are skipped as ``too_many_tracks``.
MAX_TRACKS = 1000
#: Namespaces read on input: 1.3, and 1.4 whose track elements are the same.
_INPUT_NAMESPACES = frozenset({NAMESPACE, "urn:nato:fft:protocols:nffi14"})
_NOT_ALLOWED = re.compile(r"[^A-Za-z0-9.,:*\-]")
_SIDC = re.compile(r"[A-Z0-9\-]{15}")
_COUNTRY = re.compile(r"[A-Z]{3}")
_DIGITS14 = re.compile(r"\d{14}")
#: Faster than this (km/h) is no friendly platform's speed: refused as out of range.
_MAX_SPEED_KMH = 20_000.0

Geoid = Callable[[float, float], float | None]


class NffiError(FrameError):
    """Bytes that are not an NFFI message we can read; ``problem`` says why in one word."""

    def __init__(self, problem: str, message: str) -> None:
        self.problem = problem
        super().__init__(message)


@dataclass(frozen=True, slots=True)
class NffiOptions:
    """Who releases the tracks and how they are labelled (the sink's options)."""

    system: str = "FISCHER-GW"
    country: str | None = None
    subsystem: str | None = None
    sec_policy_name: str | None = None
    sec_classification: str | None = None
    geoid: Geoid | None = None


@dataclass(frozen=True, slots=True)
class NffiTrack:
    """One track read from an NFFI message (units as in our events: m, m/s, degrees)."""

    system: str
    transponder_id: str
    time: datetime
    lat_deg: float
    lon_deg: float
    country: str | None = None
    subsystem: str | None = None
    alt_msl_m: float | None = None
    bearing_deg: float | None = None
    speed_mps: float | None = None
    unit_symbol: str | None = None
    unit_short_name: str | None = None

    @property
    def uid(self) -> str:
        """The track's identity (its trackSource): ``COUNTRY.SYSTEM.SUBSYSTEM.TRANSPONDER``."""
        parts = (self.country, self.system, self.subsystem, self.transponder_id)
        return ".".join(p for p in parts if p)


@dataclass(frozen=True, slots=True)
class ParsedMessage:
    """The tracks of one document, and the problem of each track that was skipped."""

    tracks: tuple[NffiTrack, ...]
    skipped: tuple[str, ...] = ()


# -- encoding ------------------------------------------------------------------------------


def fit_identifier(text: str, max_length: int) -> str:
    """``text`` in the schema's identifier alphabet (``[A-Za-z0-9.,:*-]``), at most
    ``max_length`` characters: accents are dropped (``Å`` is ``A``), other characters become
    ``-``, and empty becomes ``-``."""
    plain = "".join(c for c in unicodedata.normalize("NFKD", text) if not unicodedata.combining(c))
    return _NOT_ALLOWED.sub("-", plain)[:max_length] or "-"


def track_uid(opts: NffiOptions, transponder: str) -> str:
    """The uid (``NffiTrack.uid``) a reader gives our track of ``transponder``."""
    parts = (
        opts.country,
        fit_identifier(opts.system, 30),
        fit_identifier(opts.subsystem, 30) if opts.subsystem else None,
        fit_identifier(transponder, 60),
    )
    return ".".join(p for p in parts if p)


def nffi_time(time: datetime) -> str:
    """``YYYYMMDDhhmmss`` in UTC (the schema's dateTimeType); fractions are dropped."""
    return time.astimezone(UTC).strftime("%Y%m%d%H%M%S")


def _number(value: float) -> str:
    text = f"{value:.7f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _element(tag: str, value: str, **attrs: str | None) -> str:
    attributes = "".join(f" {k}={quoteattr(v)}" for k, v in attrs.items() if v is not None)
    return f"<{tag}{attributes}>{escape(value)}</{tag}>"


@lru_cache(maxsize=64)
def _releaser(opts: NffiOptions) -> tuple[str, str]:
    """The ``sourceSystem`` children and the security-label attributes: the same every track."""
    system = "".join(
        (
            _element("country", opts.country) if opts.country else "",
            _element("system", fit_identifier(opts.system, 30)),
            _element("subsystem", fit_identifier(opts.subsystem, 30)) if opts.subsystem else "",
        )
    )
    labels = {"secPolicyName": opts.sec_policy_name, "secClassification": opts.sec_classification}
    return system, "".join(f" {k}={quoteattr(v)}" for k, v in labels.items() if v is not None)


def _course_speed(event: Telemetry | BlueForce) -> tuple[float | None, float | None]:
    if isinstance(event, BlueForce):
        return event.course_deg, event.speed_mps
    if event.velocity is not None:
        north, east = event.velocity.north_mps, event.velocity.east_mps
        return math.degrees(math.atan2(east, north)), math.hypot(north, east)
    return event.heading_deg, event.groundspeed_mps


def _altitude_msl(position: Position, geoid: Geoid | None) -> float | None:
    if position.alt_msl_m is not None and math.isfinite(position.alt_msl_m):
        return position.alt_msl_m
    if position.alt_hae_m is not None and math.isfinite(position.alt_hae_m) and geoid:
        undulation = geoid(position.lat_deg, position.lon_deg)
        if undulation is not None:
            return position.alt_hae_m - undulation
    return None


def _bearing(course_deg: float | None) -> str | None:
    if course_deg is None or not math.isfinite(course_deg):
        return None
    # Rounded before the modulo, so 359.99999999 is 0, never "360" (bearing must be < 360).
    return _number(round(course_deg, 4) % 360.0)


def _speed_kmh(speed_mps: float | None) -> str | None:
    if speed_mps is None or not math.isfinite(speed_mps) or speed_mps < 0:
        return None
    return _number(round(speed_mps * KMH_PER_MPS, 3))


def encode_track(event: Event, opts: NffiOptions) -> str | None:
    """One ``track`` element for ``event``; None when it has none (no position, other kind)."""
    if isinstance(event, Telemetry):
        position = event.position
        transponder = event.airframe
        sidc = own_symbol(event.mav_type).sidc_2525c
        short_name = event.airframe
    elif isinstance(event, BlueForce):
        position = event.position
        transponder = event.uid
        sidc = event.sidc or "SFGP-----------"  # a friendly ground unit of unknown kind
        short_name = event.callsign or event.uid
    else:
        return None
    if position is None or not (
        math.isfinite(position.lat_deg) and math.isfinite(position.lon_deg)
    ):
        return None
    if position.lat_deg == 0.0 and position.lon_deg == 0.0:
        return None  # no fix: never a track at Null Island
    system, labels = _releaser(opts)
    longitude = _number(position.lon_deg)
    if longitude.startswith("-180") and float(longitude) <= -180.0:
        longitude = "180"  # the same meridian: the schema's longitude is (-180, 180]
    coordinates = _element("latitude", _number(position.lat_deg)) + _element("longitude", longitude)
    altitude = _altitude_msl(position, opts.geoid)
    if altitude is not None:
        coordinates += _element("altitude", _number(altitude))
    course, speed = _course_speed(event)
    bearing, speed_kmh = _bearing(course), _speed_kmh(speed)
    positional = (
        f"<trackSource><sourceSystem>{system}</sourceSystem>"
        + _element("transponderId", fit_identifier(transponder, 60))
        + "</trackSource>"
        + _element("dateTime", nffi_time(event.time))
        + f"<coordinates>{coordinates}</coordinates>"
        + (_element("bearing", bearing) if bearing is not None else "")
        + (_element("speed", speed_kmh) if speed_kmh is not None else "")
    )
    symbol = sidc.replace("*", "-")
    identification = _element("unitSymbol", symbol) + _element(
        "unitShortName", fit_identifier(short_name, 15)
    )
    return (
        f"<track><positionalData{labels}>{positional}</positionalData>"
        f"<identificationData{labels}>{identification}</identificationData></track>"
    )


def encode_message(tracks: Iterable[str]) -> bytes:
    """One NFFI document (XML declaration, ``NFFIMessage``) of ``tracks``, ending in a newline.

    No tracks is a legal, empty message (a heartbeat).
    """
    body = "".join(tracks)
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<NFFIMessage xmlns="{NAMESPACE}">{body}</NFFIMessage>\n'
    ).encode()


# -- parsing -------------------------------------------------------------------------------


def _local(tag: object) -> tuple[str | None, str]:
    if not isinstance(tag, str):
        return None, ""  # a comment or processing instruction
    if tag.startswith("{"):
        namespace, _, local = tag[1:].partition("}")
        return namespace, local
    return None, tag


def _children(parent: ET.Element | None) -> dict[str, ET.Element]:
    """``parent``'s child elements by local name (the first of each name wins)."""
    found: dict[str, ET.Element] = {}
    if parent is not None:
        for child in parent:
            tag = child.tag
            if isinstance(tag, str):
                found.setdefault(tag.rpartition("}")[2], child)
    return found


def _text(children: dict[str, ET.Element], name: str) -> str | None:
    child = children.get(name)
    if child is None or child.text is None:
        return None
    return child.text.strip() or None


class _TrackProblem(Exception):
    def __init__(self, problem: str) -> None:
        self.problem = problem


def _float(children: dict[str, ET.Element], name: str, low: float, high: float) -> float | None:
    text = _text(children, name)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise _TrackProblem(name) from None
    if not (math.isfinite(value) and low <= value <= high):
        raise _TrackProblem(name)
    return value


def _time(stamp: str | None) -> datetime:
    if stamp is None or not _DIGITS14.fullmatch(stamp):
        raise _TrackProblem("dateTime")
    try:
        return datetime(
            int(stamp[0:4]), int(stamp[4:6]), int(stamp[6:8]),
            int(stamp[8:10]), int(stamp[10:12]), int(stamp[12:14]), tzinfo=UTC,
        )  # fmt: skip
    except ValueError:  # month 13, 30 February, hour 24 ...
        raise _TrackProblem("dateTime") from None


def _track(element: ET.Element) -> NffiTrack:
    parts = _children(element)
    if "positionalData" not in parts:
        raise _TrackProblem("positionalData")
    positional = _children(parts["positionalData"])
    source = _children(positional.get("trackSource"))
    system_parts = _children(source.get("sourceSystem"))
    system = _text(system_parts, "system")
    transponder = _text(source, "transponderId")
    if not system or not transponder or len(system) > 30 or len(transponder) > 60:
        raise _TrackProblem("trackSource")
    if _NOT_ALLOWED.search(system) or _NOT_ALLOWED.search(transponder):
        raise _TrackProblem("trackSource")
    country = _text(system_parts, "country")
    if country is not None and not _COUNTRY.fullmatch(country):
        raise _TrackProblem("country")
    subsystem = _text(system_parts, "subsystem")
    if subsystem is not None and (len(subsystem) > 30 or _NOT_ALLOWED.search(subsystem)):
        raise _TrackProblem("subsystem")
    time = _time(_text(positional, "dateTime"))
    coordinates = _children(positional.get("coordinates"))
    lat = _float(coordinates, "latitude", -90.0, 90.0)
    lon = _float(coordinates, "longitude", -180.0, 180.0)
    if lat is None or lon is None or lon == -180.0:
        raise _TrackProblem("coordinates")
    altitude = _float(coordinates, "altitude", -12_000.0, 100_000.0)
    bearing = _float(positional, "bearing", 0.0, 360.0)
    if bearing == 360.0:
        raise _TrackProblem("bearing")
    speed_kmh = _float(positional, "speed", 0.0, _MAX_SPEED_KMH)
    identification = _children(parts.get("identificationData"))
    symbol = _text(identification, "unitSymbol")
    if symbol is not None and not _SIDC.fullmatch(symbol):
        raise _TrackProblem("unitSymbol")
    short_name = _text(identification, "unitShortName")
    if short_name is not None and (len(short_name) > 15 or _NOT_ALLOWED.search(short_name)):
        raise _TrackProblem("unitShortName")
    return NffiTrack(
        system=system,
        transponder_id=transponder,
        time=time,
        lat_deg=lat,
        lon_deg=lon,
        country=country,
        subsystem=subsystem,
        alt_msl_m=altitude,
        bearing_deg=bearing,
        speed_mps=None if speed_kmh is None else speed_kmh / KMH_PER_MPS,
        unit_symbol=symbol,
        unit_short_name=short_name,
    )


def parse_message(data: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> ParsedMessage:
    """The tracks of one NFFI document; ``NffiError`` if it is not one we can read.

    Problems: ``oversize``, ``dtd`` (DTDs, entities, external references), ``xml`` (not
    well-formed), ``root`` (not an ``NFFIMessage`` of NFFI 1.3/1.4). Tracks are checked one
    by one: a bad one is skipped (its problem is in ``skipped``: the element that was
    missing or out of range), the others are returned.
    """
    if len(data) > max_bytes:
        raise NffiError("oversize", f"NFFI message of {len(data)} bytes exceeds {max_bytes}")
    try:
        root = fromstring(data, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except DefusedXmlException as exc:
        raise NffiError(
            "dtd", f"DTDs, entities and external references are refused: {exc}"
        ) from exc
    except (ET.ParseError, ValueError, LookupError, RecursionError) as exc:
        # ValueError/LookupError: an encoding declaration Python does not know.
        raise NffiError("xml", f"not well-formed XML: {type(exc).__name__}") from exc
    namespace, local = _local(root.tag)
    if local != "NFFIMessage" or (namespace is not None and namespace not in _INPUT_NAMESPACES):
        raise NffiError("root", "the root element is not an NFFI 1.3 NFFIMessage")
    tracks: list[NffiTrack] = []
    skipped: list[str] = []
    for element in root:
        if str(element.tag).rpartition("}")[2] != "track":
            continue
        if len(tracks) + len(skipped) >= MAX_TRACKS:
            skipped.append("too_many_tracks")
            break
        try:
            tracks.append(_track(element))
        except _TrackProblem as problem:
            skipped.append(problem.problem)
    return ParsedMessage(tuple(tracks), tuple(skipped))


def tracks_of(events: Sequence[Event], opts: NffiOptions) -> list[str]:
    """The ``track`` elements of ``events`` that have one, in order."""
    return [t for e in events if (t := encode_track(e, opts)) is not None]
