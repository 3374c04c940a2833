"""Text from peers (callsigns, remarks), made safe to show, and marked with where it came from.

A callsign in a CoT event is whatever the sender typed, and anyone who reaches a CoT port is a
sender. ``safe_text`` restricts such text before a cue, a CDM or the story shows it:

- Unicode is normalised (NFKC: full-width and other look-alike forms fold to plain letters);
  a letter with an accent outside the alphabet keeps its base letter (é to e);
- control characters, bidirectional overrides, zero-width and other format characters are
  removed; any run of white space becomes one space, trimmed at both ends;
- what remains is kept only if it is in ``ALPHABET`` (ASCII letters, Å Ä Ö å ä ö, digits,
  space and ``- . / _ : ?``); any other character becomes ``?``;
- the result is at most ``max_chars`` long (``MAX_CHARS`` by default): longer text is cut and
  ends in ``...``. Only the first ``MAX_INPUT_CHARS`` of the input are read.

The function is idempotent, so text made safe at its source and again where it is shown is
unchanged by the second pass.

An alphabet does not stop ``WEAPONS FREE - ENGAGE AUTHORISED BY BDE``: that is all letters.
So text from a peer is never shown bare: every display says what kind of text it is and how
far its sender was checked (``Provenance``, kept with the events in ``gateway.events``),
e.g. ``"WEAPONS FREE - ENGAGE AUTHORISED" (unauthenticated CoT callsign, source atak-mesh)``.
``callsign_provenance`` gives that label, ``shown`` (or ``marked``, given the label) the
whole quoted, marked form (quotes are outside the alphabet, so the text cannot close them).
"""

from __future__ import annotations

import string
import unicodedata

from gateway.events import Provenance

__all__ = [
    "ALPHABET",
    "MAX_CHARS",
    "MAX_INPUT_CHARS",
    "Provenance",
    "callsign_provenance",
    "marked",
    "protocol_of",
    "safe_text",
    "shown",
]

#: Every character ``safe_text`` may return.
ALPHABET = frozenset(string.ascii_letters + string.digits + "ÅÄÖåäö" + " -./_:?")
#: The default length cap: longer than any real callsign (ATAK's are a few words).
MAX_CHARS = 32
#: How much of the input is looked at; the rest is ignored (bounds the work per string).
MAX_INPUT_CHARS = 1024
_CUT = "..."
_REPLACEMENT = "?"


_QUALIFIER = {
    Provenance.CONFIGURED: "configured",
    Provenance.AUTHENTICATED: "certificate-authenticated",
    Provenance.ADDRESS_ONLY: "unauthenticated (allow-listed address)",
    Provenance.UNAUTHENTICATED: "unauthenticated",
}
_PROTOCOLS = {"cot": "CoT", "nffi": "NFFI"}


def protocol_of(source: str) -> str:
    """The protocol a BlueForce ``source`` names, as people write it: ``cot`` is ``CoT``.

    ``config:NAME`` (a unit fixed in a processor's config) is ``config``.
    """
    if source.startswith("config"):
        return "config"
    return _PROTOCOLS.get(source, safe_text(source, 16) or "unknown")


def callsign_provenance(provenance: Provenance, source: str) -> str:
    """What a callsign from ``source`` with ``provenance`` is, in words.

    ``unauthenticated CoT callsign``, ``certificate-authenticated NFFI callsign``,
    ``unauthenticated (allow-listed address) NFFI callsign``, ``configured callsign``.
    """
    if provenance is Provenance.CONFIGURED:
        return "configured callsign"
    return f"{_QUALIFIER[provenance]} {protocol_of(source)} callsign"


def shown(text: str, provenance: Provenance, source: str, source_name: str = "") -> str:
    """Peer text as a display shows it: safe, quoted, and marked with its provenance.

    ``"WEAPONS FREE - ENGAGE AUTHORISED" (unauthenticated CoT callsign, source atak-mesh)``.
    """
    return marked(text, callsign_provenance(provenance, source), source_name)


def marked(text: str, label: str | None, source_name: str | None = None) -> str:
    """``text`` made safe, quoted, followed by ``label`` and the source's name in brackets.

    A ``label`` of None (a record from before provenance was kept) reads "callsign of
    unknown provenance": never bare.
    """
    where = f", source {safe_text(source_name, 64)}" if source_name else ""
    return f'"{safe_text(text)}" ({label or "callsign of unknown provenance"}{where})'


def safe_text(text: str, max_chars: int = MAX_CHARS) -> str:
    """``text`` restricted to ``ALPHABET`` and ``max_chars``; see the module docstring."""
    if max_chars < len(_CUT) + 1:
        raise ValueError(f"max_chars must be at least {len(_CUT) + 1}, got {max_chars}")
    kept: list[str] = []
    for char in unicodedata.normalize("NFKC", text[:MAX_INPUT_CHARS]):
        if char in ALPHABET:
            kept.append(char)
        elif char.isspace():
            kept.append(" ")
        elif unicodedata.category(char)[0] in "CM":
            continue  # controls, format (bidi, zero-width), unassigned, combining marks
        else:
            base = unicodedata.normalize("NFKD", char)[:1]
            kept.append(base if base in ALPHABET and base != " " else _REPLACEMENT)
    result = " ".join("".join(kept).split())
    if len(result) > max_chars:
        result = result[: max_chars - len(_CUT)].rstrip() + _CUT
    return result
