"""Peer text (callsigns, remarks): a safe alphabet and length, marked by provenance."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.domain.peertext import (
    ALPHABET,
    MAX_CHARS,
    Provenance,
    callsign_provenance,
    marked,
    safe_text,
    shown,
)

HOSTILE = "WEAPONS FREE - ENGAGE AUTHORISED BY BDE"


@given(st.text(max_size=3000), st.integers(4, 200))
def test_the_output_is_always_in_the_alphabet_and_bounded(text: str, max_chars: int) -> None:
    safe = safe_text(text, max_chars)
    assert set(safe) <= ALPHABET
    assert len(safe) <= max_chars
    assert safe == safe.strip()
    assert "  " not in safe
    assert safe_text(safe, max_chars) == safe  # idempotent: safe at the source and when shown


@given(st.text(alphabet=sorted(ALPHABET - {" "}), min_size=1, max_size=MAX_CHARS))
def test_text_already_safe_is_kept_as_it_is(text: str) -> None:
    assert safe_text(text) == text


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("1. pluton", "1. pluton"),
        ("Ärlan Östra Å/3", "Ärlan Östra Å/3"),
        ("A\u0308rlan", "Ärlan"),  # decomposed Ä composes
        ("ＶＩＤＡＲ　１", "VIDAR 1"),  # full-width forms fold to ASCII
        ("Zoë Ærø", "Zoe ?r?"),  # an accent outside the alphabet keeps its base letter
        ("ALFA\u202e1 ATEB", "ALFA1 ATEB"),  # a bidi override is removed
        ("AL\u200bFA\u200d7\ufeff", "ALFA7"),  # zero-width characters are removed
        ("ALFA\x1b[31m7\x00", "ALFA?31m7"),  # controls removed
        ("ALFA\t\n\r  7 ", "ALFA 7"),  # white space collapses
        ('<b>"x"</b>; rm -rf', "?b??x??/b?? rm -rf"),
        ("\u200b\u202e", ""),
    ],
)
def test_examples(text: str, expected: str) -> None:
    assert safe_text(text) == expected


def test_long_text_is_cut_and_says_so() -> None:
    assert safe_text(HOSTILE) == "WEAPONS FREE - ENGAGE AUTHORI..."
    assert len(safe_text("x" * 100_000)) == MAX_CHARS


def test_a_cap_too_small_for_the_cut_mark_is_refused() -> None:
    with pytest.raises(ValueError, match="max_chars"):
        safe_text("abc", 3)


def test_each_provenance_says_what_the_callsign_is() -> None:
    assert callsign_provenance(Provenance.UNAUTHENTICATED, "cot") == "unauthenticated CoT callsign"
    assert (
        callsign_provenance(Provenance.AUTHENTICATED, "nffi")
        == "certificate-authenticated NFFI callsign"
    )
    assert (
        callsign_provenance(Provenance.ADDRESS_ONLY, "nffi")
        == "unauthenticated (allow-listed address) NFFI callsign"
    )
    assert callsign_provenance(Provenance.CONFIGURED, "config:cuas") == "configured callsign"
    # A source the module does not know is named, made safe, never trusted by its name.
    assert callsign_provenance(Provenance.UNAUTHENTICATED, 'x"y') == "unauthenticated x?y callsign"


def test_a_callsign_is_never_shown_bare() -> None:
    assert shown(HOSTILE, Provenance.UNAUTHENTICATED, "cot", "atak-mesh") == (
        '"WEAPONS FREE - ENGAGE AUTHORI..." (unauthenticated CoT callsign, source atak-mesh)'
    )
    # The text cannot close the quotes or the brackets itself.
    assert shown('X" (configured callsign)', Provenance.UNAUTHENTICATED, "cot") == (
        '"X? ?configured callsign?" (unauthenticated CoT callsign)'
    )
    assert marked("VIDAR 1", None) == '"VIDAR 1" (callsign of unknown provenance)'
