"""The Ra 180 Compact Data Message (CDM): a hostile track as one line of at most 127 characters.

``compose(track, ...)`` turns a ``Track`` into a ``Cdm`` (its fields, already in radio form);
``Cdm.text(max_chars)`` writes it, dropping optional fields (originator, then speed, then
course) until it fits and never cutting a field; ``parse_cdm`` reads a line back (tests, and
anything that listens on the net) and raises ``CdmError`` for anything else. The grammar,
the abbreviation table and the character set are documented in docs/ra180.md::

    MAL FIENDE LUFT-MUN POS 33VXH 4567 1234 KONF 094 TID 251958ZNOV26 NR 0017 KURS 045 FART 120

Every character is from ``CHARSET`` (upper-case A-Z, digits, space, ``-`` and ``/``): Swedish
letters are transliterated without their marks (Å, Ä → A; Ö → O), as the data terminals of
the net take 7-bit text only. The Swedish announcement of the same message, with digits read
as in radio procedure, is ``sinks.ra180.phrases``.
"""

from __future__ import annotations

import math
import re
import unicodedata
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import Literal

from gateway.domain.geodesy import MgrsError, from_mgrs, to_mgrs
from gateway.errors import GatewayError
from gateway.events import Track

__all__ = [
    "CHARSET",
    "CLASS_ABBREVIATIONS",
    "HOSTILITY_WORDS",
    "MANDATORY_MAX_CHARS",
    "MAX_ABBREVIATION_CHARS",
    "MAX_CDM_CHARS",
    "MAX_ORIGINATOR_CHARS",
    "Cdm",
    "CdmError",
    "CdmPrecision",
    "MessageType",
    "compose",
    "parse_cdm",
    "radio_text",
]

#: The longest message a Ra 180 data terminal takes.
MAX_CDM_CHARS = 127
#: Every character a message may hold.
CHARSET = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 -/")
#: Class abbreviations and originators at most this long (so the mandatory part always fits).
MAX_ABBREVIATION_CHARS = 16
MAX_ORIGINATOR_CHARS = 16

MessageType = Literal["MAL", "UPPD"]
CdmPrecision = Literal[1, 10]

#: Object class (``Track.object_class``) → its abbreviation on the net (Swedish, transliterated).
CLASS_ABBREVIATIONS: dict[str, str] = {
    "tank": "STRV",  # stridsvagn
    "armour": "PANS",  # pansarförband
    "infantry_platoon": "INF-PLUT",  # infanteripluton
    "uav": "UAV",  # obemannad luftfarkost
    "loitering_munition": "LUFT-MUN",  # kringsvävande ammunition (luftburen)
    "other": "OBJ",  # objekt: a class outside the fusion frame
}
#: Track hostility → the word on the net. Neutral and friendly tracks are never sent.
HOSTILITY_WORDS: dict[str, str] = {"hostile": "FIENDE", "suspect": "MISST", "unknown": "OKAND"}
_MONTHS = ("JAN", "FEB", "MAR", "APR", "MAY", "JUN", "JUL", "AUG", "SEP", "OCT", "NOV", "DEC")

#: The longest the mandatory fields can be: "UPPD FIENDE " + the longest class abbreviation +
#: " POS 33VXH 45678 12345 KONF 100 TID 251958ZNOV26 NR 0017".
MANDATORY_MAX_CHARS = (
    len("UPPD ")
    + max(len(word) for word in HOSTILITY_WORDS.values())
    + 1
    + MAX_ABBREVIATION_CHARS
    + len(" POS 33VXH 45678 12345 KONF 100 TID 251958ZNOV26 NR 0017")
)
_TOKEN = re.compile(r"[A-Z0-9/-]+")
_MGRS = re.compile(r"^(\d{1,2}[C-HJ-NP-X][A-HJ-NP-Z]{2}) (\d{4}|\d{5}) (\d{4}|\d{5})$")
_DTG = re.compile(r"^(\d{2})(\d{2})(\d{2})Z([A-Z]{3})(\d{2})$")
_LINE = re.compile(
    r"^(?P<type>MAL|UPPD) (?P<hostility>[A-Z]+) (?P<cls>[A-Z0-9/-]{1,16}) "
    r"POS (?P<mgrs>\S+ \S+ \S+) KONF (?P<conf>\d{3}) TID (?P<dtg>\S+) NR (?P<nr>\d{4})"
    r"(?: KURS (?P<course>\d{3}))?(?: FART (?P<speed>\d{3}))?(?: FRAN (?P<orig>[A-Z0-9/-]+))?$"
)


class CdmError(GatewayError, ValueError):
    """Raised for a track a CDM cannot carry, or text that is not a CDM (naming the input)."""


def radio_text(text: str) -> str:
    """``text`` in the net's character set: upper case, marks dropped (Å Ä → A, Ö → O).

    Characters that have no place in ``CHARSET`` even then are left out; callers that take
    operator input check the result is unchanged in meaning (``CdmError`` is theirs to raise).
    """
    decomposed = unicodedata.normalize("NFKD", text.upper())
    plain = "".join(c for c in decomposed if not unicodedata.combining(c))
    return "".join(c for c in plain if c in CHARSET)


def _token(value: str, what: str, limit: int) -> str:
    converted = radio_text(value)
    if not converted or not _TOKEN.fullmatch(converted) or len(converted) > limit:
        raise CdmError(
            f"{what} {value!r}: expected 1 to {limit} of A-Z, 0-9, '-' or '/' "
            f"(Swedish letters are transliterated), no spaces"
        )
    return converted


def check_abbreviation(value: str) -> str:
    """An operator's class abbreviation in radio form; ``CdmError`` naming it if unusable."""
    return _token(value, "class abbreviation", MAX_ABBREVIATION_CHARS)


def check_originator(value: str) -> str:
    """An operator's originator (call sign) in radio form; ``CdmError`` naming it if unusable."""
    return _token(value, "originator", MAX_ORIGINATOR_CHARS)


def dtg(time: datetime) -> str:
    """The date-time group of ``time`` in UTC: ``DDHHMMZMONYY`` (``251958ZNOV26``)."""
    t = time.astimezone(UTC)
    return f"{t.day:02d}{t.hour:02d}{t.minute:02d}Z{_MONTHS[t.month - 1]}{t.year % 100:02d}"


def mgrs_field(lat_deg: float, lon_deg: float, precision_m: CdmPrecision) -> str:
    """``33VXH 4567 1234`` (10 m) or ``33VXH 45678 12345`` (1 m); ``CdmError`` if polar."""
    try:
        compact = to_mgrs(lat_deg, lon_deg, precision_m)
    except MgrsError as exc:
        raise CdmError(f"no MGRS for lat {lat_deg}, lon {lon_deg}: {exc}") from exc
    digits = 5 if precision_m == 1 else 4
    head, easting, northing = (
        compact[: -2 * digits],
        compact[-2 * digits : -digits],
        compact[-digits:],
    )
    return f"{head} {easting} {northing}"


@dataclass(frozen=True, slots=True)
class Cdm:
    """One Compact Data Message, its fields already in radio form.

    ``number`` is the sink's 4-digit target number (the same for every message about one
    track); ``confidence_pct`` 0..100; ``course_deg`` 0..359 and ``speed_kmh`` 0..999 are
    optional, as is ``originator``.
    """

    type: MessageType
    hostility: str
    class_abbreviation: str
    mgrs: str
    confidence_pct: int
    dtg: str
    number: int
    course_deg: int | None = None
    speed_kmh: int | None = None
    originator: str | None = None

    def fields(self) -> list[str]:
        """The message's fields in order, each as written (``KONF 094``)."""
        out = [
            self.type,
            self.hostility,
            self.class_abbreviation,
            f"POS {self.mgrs}",
            f"KONF {self.confidence_pct:03d}",
            f"TID {self.dtg}",
            f"NR {self.number:04d}",
        ]
        if self.course_deg is not None:
            out.append(f"KURS {self.course_deg:03d}")
        if self.speed_kmh is not None:
            out.append(f"FART {self.speed_kmh:03d}")
        if self.originator is not None:
            out.append(f"FRAN {self.originator}")
        return out

    def fitted(self, max_chars: int = MAX_CDM_CHARS) -> Cdm:
        """This message with optional fields dropped until it fits in ``max_chars``.

        Drops the originator, then the speed, then the course; never cuts or drops a
        mandatory field: ``CdmError`` if even those do not fit.
        """
        shorter = (
            replace(self, originator=None),
            replace(self, originator=None, speed_kmh=None),
            replace(self, originator=None, speed_kmh=None, course_deg=None),
        )
        for cdm in (self, *shorter):
            if len(" ".join(cdm.fields())) <= max_chars:
                return cdm
        mandatory = " ".join(shorter[-1].fields())
        raise CdmError(f"the mandatory fields {mandatory!r} exceed {max_chars} characters")

    def text(self, max_chars: int = MAX_CDM_CHARS) -> str:
        """The message as sent: fields separated by one space, fitted to ``max_chars``."""
        return " ".join(self.fitted(max_chars).fields())


def compose(
    track: Track,
    *,
    message_type: MessageType,
    number: int,
    precision_m: CdmPrecision = 10,
    abbreviations: dict[str, str] | None = None,
    originator: str | None = None,
    min_speed_mps: float = 0.5,
) -> Cdm:
    """The CDM of ``track``; ``CdmError`` for a hostility never sent or a polar position.

    An object class missing from ``abbreviations`` (default ``CLASS_ABBREVIATIONS``) is sent
    as ``OBJ``. Course and speed are given only when the track moves at ``min_speed_mps`` or
    more (the course of a standing target is noise).
    """
    word = HOSTILITY_WORDS.get(track.hostility)
    if word is None:
        raise CdmError(f"track {track.track_id}: a {track.hostility} track is never sent")
    if not 0 <= number <= 9999:
        raise CdmError(f"target number {number} is not 0..9999")
    table = CLASS_ABBREVIATIONS if abbreviations is None else abbreviations
    abbreviation = table.get(track.object_class) or table.get("other") or "OBJ"
    course = speed = None
    if (
        track.speed_mps is not None
        and track.course_deg is not None
        and math.isfinite(track.speed_mps)  # a Track allows inf; the net hears none then
        and track.speed_mps >= min_speed_mps
    ):
        course = round(track.course_deg) % 360
        speed = round(min(track.speed_mps * 3.6, 999.0))
    return Cdm(
        type=message_type,
        hostility=word,
        class_abbreviation=abbreviation,
        mgrs=mgrs_field(track.position.lat_deg, track.position.lon_deg, precision_m),
        confidence_pct=min(100, max(0, round(track.confidence * 100))),
        dtg=dtg(track.time),
        number=number,
        course_deg=course,
        speed_kmh=speed,
        originator=originator,
    )


def parse_cdm(text: str) -> Cdm:
    """Read one CDM back; ``CdmError`` naming the text for anything that is not one.

    Checks the character set, the length, each field's form and range, and that the grid
    reference decodes (``gateway.domain.geodesy.from_mgrs``).
    """
    shown = text[:160]
    if len(text) > MAX_CDM_CHARS:
        raise CdmError(f"{shown!r}: {len(text)} characters, more than {MAX_CDM_CHARS}")
    if not set(text) <= CHARSET:
        raise CdmError(f"{shown!r}: characters outside the Ra 180 set")
    match = _LINE.match(text)
    if match is None:
        raise CdmError(f"{shown!r}: not a CDM")
    hostility = match["hostility"]
    if hostility not in HOSTILITY_WORDS.values():
        raise CdmError(f"{shown!r}: unknown hostility {hostility!r}")
    grid = _MGRS.match(match["mgrs"])
    if grid is None or len(grid[2]) != len(grid[3]):
        raise CdmError(f"{shown!r}: not a 1 m or 10 m MGRS reference: {match['mgrs']!r}")
    try:
        from_mgrs(match["mgrs"])
    except MgrsError as exc:
        raise CdmError(f"{shown!r}: {exc}") from exc
    when = _DTG.match(match["dtg"])
    if when is None or when[4] not in _MONTHS:
        raise CdmError(f"{shown!r}: not a date-time group: {match['dtg']!r}")
    day, hour, minute = int(when[1]), int(when[2]), int(when[3])
    if not (1 <= day <= 31 and hour <= 23 and minute <= 59):
        raise CdmError(f"{shown!r}: not a date-time group: {match['dtg']!r}")
    confidence = int(match["conf"])
    course = None if match["course"] is None else int(match["course"])
    if confidence > 100 or (course is not None and course > 359):
        raise CdmError(f"{shown!r}: confidence or course out of range")
    return Cdm(
        type="MAL" if match["type"] == "MAL" else "UPPD",
        hostility=hostility,
        class_abbreviation=match["cls"],
        mgrs=match["mgrs"],
        confidence_pct=confidence,
        dtg=match["dtg"],
        number=int(match["nr"]),
        course_deg=course,
        speed_kmh=None if match["speed"] is None else int(match["speed"]),
        originator=match["orig"],
    )
