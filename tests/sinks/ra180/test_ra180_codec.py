"""The Ra 180 CDM codec: length, character set, MGRS against the ``mgrs`` package, truncation."""

from __future__ import annotations

import contextlib
import math
from datetime import UTC, datetime, timedelta
from pathlib import Path

import mgrs
import pytest
from geographiclib.geodesic import Geodesic
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.events import Position, Track
from sinks.ra180.cdm import (
    CHARSET,
    CLASS_ABBREVIATIONS,
    MANDATORY_MAX_CHARS,
    MAX_CDM_CHARS,
    Cdm,
    CdmError,
    check_originator,
    compose,
    parse_cdm,
    radio_text,
)
from sinks.ra180.phrases import DIGIT_WORDS, announcement, spell

T0 = datetime(2026, 11, 25, 19, 58, 12, tzinfo=UTC)
DECODER = mgrs.MGRS()


def track(
    lat: float = 58.4108,
    lon: float = 15.6214,
    *,
    object_class: str = "loitering_munition",
    hostility: str = "hostile",
    confidence: float = 0.94,
    speed_mps: float | None = None,
    course_deg: float | None = None,
    time: datetime = T0,
) -> Track:
    return Track(
        event_id="e",
        track_id="T-1",
        time=time,
        object_class=object_class,
        confidence=confidence,
        position=Position(lat_deg=lat, lon_deg=lon),
        cep50_m=5.0,
        cep90_m=9.0,
        speed_mps=speed_mps,
        course_deg=course_deg,
        first_seen=time,
        last_seen=time,
        hostility=hostility,  # type: ignore[arg-type]
    )


tracks = st.builds(
    track,
    lat=st.floats(-79.999, 83.999),
    lon=st.floats(-180.0, 180.0),
    object_class=st.sampled_from([*CLASS_ABBREVIATIONS, "bicycle", ""]),
    hostility=st.sampled_from(["hostile", "suspect", "unknown"]),
    confidence=st.floats(0.0, 1.0),
    speed_mps=st.none() | st.floats(0.0, 1000.0) | st.floats(0.0, allow_nan=False),
    course_deg=st.none() | st.floats(0.0, 359.999),
    time=st.datetimes(
        min_value=datetime(2000, 1, 1),  # noqa: DTZ001 - hypothesis takes naive bounds
        max_value=datetime(2099, 12, 31),  # noqa: DTZ001 - and adds the zone itself
        timezones=st.just(UTC),
    ),
)
originators = st.none() | st.text(
    alphabet="ABCDEFGHIJKLMNOPQRSTUVWXYZÅÄÖ0123456789-/", min_size=1, max_size=16
)


class TestExample:
    """One message written out, as an operator reads it."""

    def test_a_loitering_munition_at_10_m(self) -> None:
        cdm = compose(track(), message_type="MAL", number=17)
        assert cdm.text() == (
            "MAL FIENDE LUFT-MUN POS 33VWE 3630 7461 KONF 094 TID 251958ZNOV26 NR 0017"
        )

    def test_course_speed_and_originator_at_1_m(self) -> None:
        moving = track(speed_mps=33.4, course_deg=44.6)
        cdm = compose(moving, message_type="UPPD", number=3, precision_m=1, originator="JAGARE1")
        assert cdm.text() == (
            "UPPD FIENDE LUFT-MUN POS 33VWE 36308 74614 KONF 094 TID 251958ZNOV26 NR 0003 "
            "KURS 045 FART 120 FRAN JAGARE1"
        )

    def test_a_standing_target_has_no_course(self) -> None:
        cdm = compose(track(speed_mps=0.2, course_deg=270.0), message_type="MAL", number=1)
        assert (cdm.course_deg, cdm.speed_kmh) == (None, None)

    def test_friends_and_neutrals_are_never_sent(self) -> None:
        for hostility in ("friend", "neutral"):
            with pytest.raises(CdmError, match="never sent"):
                compose(track(hostility=hostility), message_type="MAL", number=1)

    def test_a_polar_track_is_refused_by_name(self) -> None:
        with pytest.raises(CdmError, match="no MGRS"):
            compose(track(lat=85.0), message_type="MAL", number=1)

    def test_swedish_letters_are_transliterated(self) -> None:
        assert radio_text("Mål för Ärna") == "MAL FOR ARNA"
        assert check_originator("Rödöga-2") == "RODOGA-2"
        with pytest.raises(CdmError, match="originator"):
            check_originator("two words")


class TestProperties:
    """Every message fits, uses the set, and points where the track is."""

    @settings(max_examples=300, deadline=None)
    @given(tracks, st.sampled_from([1, 10]), st.sampled_from(["MAL", "UPPD"]), originators)
    def test_every_cdm_fits_the_charset_and_its_mgrs_decodes_to_the_track(
        self, t: Track, precision: int, kind: str, originator: str | None
    ) -> None:
        cdm = compose(
            t,
            message_type=kind,  # type: ignore[arg-type]
            number=9999,
            precision_m=precision,  # type: ignore[arg-type]
            originator=None if originator is None else check_originator(originator),
        )
        text = cdm.text()
        assert len(text) <= MAX_CDM_CHARS
        assert set(text) <= CHARSET
        assert parse_cdm(text) == cdm  # everything fits at 127: nothing was dropped
        # The independent decoder: the mgrs package reads the cell centre back.
        lat, lon = DECODER.toLatLon(cdm.mgrs.replace(" ", ""))
        distance = Geodesic.WGS84.Inverse(t.position.lat_deg, t.position.lon_deg, lat, lon)["s12"]
        assert distance <= precision * math.sqrt(2) / 2 * 1.01 + 1e-3

    @settings(max_examples=200, deadline=None)
    @given(
        tracks,
        originators,
        st.integers(MANDATORY_MAX_CHARS, MAX_CDM_CHARS),
    )
    def test_truncation_drops_optional_fields_in_order_and_never_cuts_one(
        self, t: Track, originator: str | None, max_chars: int
    ) -> None:
        full = compose(
            t,
            message_type="UPPD",
            number=1,
            precision_m=1,
            originator=None if originator is None else check_originator(originator),
            abbreviations={t.object_class: "X" * 16},
        )
        text = full.text(max_chars)
        assert len(text) <= max_chars
        fitted = parse_cdm(text)
        kept = fitted.fields()
        assert kept[:7] == full.fields()[:7]  # the mandatory fields, whole
        assert set(kept) <= set(full.fields())  # each optional one whole, or gone
        dropped = [
            name
            for name in ("originator", "speed_kmh", "course_deg")
            if getattr(full, name) is not None and getattr(fitted, name) is None
        ]
        # Only a prefix of the drop order, and only when the whole did not fit.
        order = [
            n for n in ("originator", "speed_kmh", "course_deg") if getattr(full, n) is not None
        ]
        assert dropped == order[: len(dropped)]
        assert (dropped == []) == (len(" ".join(full.fields())) <= max_chars)

    @settings(max_examples=300, deadline=None)
    @given(st.text(max_size=200) | st.binary(max_size=200).map(lambda b: b.decode("latin-1")))
    def test_parse_takes_a_cdm_or_raises_cdm_error_only(self, text: str) -> None:
        try:
            cdm = parse_cdm(text)
        except CdmError:
            return
        assert isinstance(cdm, Cdm)

    @settings(max_examples=100, deadline=None)
    @given(tracks)
    def test_parse_survives_mutations_of_real_messages(self, t: Track) -> None:
        text = compose(t, message_type="MAL", number=42).text()
        for i in range(0, len(text), 7):
            for mutated in (text[:i] + text[i + 1 :], text[:i] + "9" + text[i:]):
                with contextlib.suppress(CdmError):
                    parse_cdm(mutated)

    def test_the_mandatory_part_never_exceeds_its_bound(self) -> None:
        worst = compose(
            track(time=T0 + timedelta(days=30), confidence=1.0),
            message_type="UPPD",
            number=9999,
            precision_m=1,
            abbreviations={"loitering_munition": "X" * 16},
        )
        assert len(worst.text()) <= MANDATORY_MAX_CHARS


class TestVoiceText:
    """The spoken form: radio digits, spelled grid letters, Swedish words."""

    def test_digits_are_read_one_by_one(self) -> None:
        assert spell("0123456789") == ", ".join(DIGIT_WORDS)
        assert spell("33V") == "trea, trea, Victor"

    def test_announcement_of_a_real_cdm(self) -> None:
        cdm = compose(track(speed_mps=10.0, course_deg=90.0), message_type="MAL", number=17)
        text = announcement(cdm)
        assert text.startswith("Nytt mål, nummer nolla, nolla, etta, sju. Fiende, kringsvävande")
        assert "Position trea, trea, Victor, Whiskey, Echo. trea, sexa, trea, nolla." in text
        assert "Kurs nolla, nia, nolla." in text
        assert not any(ch.isdigit() for ch in text)


def test_the_messages_and_voice_in_the_doc_are_what_the_code_makes() -> None:
    """docs/ra180.md's example lines parse, and its spoken example is the code's."""
    doc = (Path(__file__).resolve().parents[3] / "docs" / "ra180.md").read_text()
    examples = [line for line in doc.splitlines() if line.startswith(("MAL ", "UPPD "))]
    assert len(examples) == 2
    for line in examples:
        assert " ".join(parse_cdm(line).fields()) == line
    cdm = compose(track(), message_type="MAL", number=17)
    assert cdm.text() == examples[0]
    spoken = " ".join(
        line.removeprefix("> ").strip() for line in doc.splitlines() if line.startswith(">")
    )
    assert spoken == announcement(cdm)
