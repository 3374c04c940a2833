"""The Swedish spoken announcement of a Ra 180 CDM, as text for a speech synthesiser.

``announcement(cdm)`` says what the message says, in Swedish, with every number read digit
by digit as in radio procedure (nolla, etta, tvåa, trea, fyra, femma, sexa, sju, åtta, nia)
and the letters of the grid reference in the international spelling alphabet (Alfa, Bravo,
...), so a synthesiser never reads "33" as "trettiotre". Rendering it to sound is the sink's
(``sinks/ra180/voice.py``, espeak-ng's ``sv`` voice).
"""

from __future__ import annotations

from sinks.ra180.cdm import CLASS_ABBREVIATIONS, Cdm

__all__ = ["DIGIT_WORDS", "SPELLING", "announcement", "spell"]

#: Digits as read in Swedish radio procedure.
DIGIT_WORDS = ("nolla", "etta", "tvåa", "trea", "fyra", "femma", "sexa", "sju", "åtta", "nia")
#: Letters as spelled on the net (the ICAO / NATO spelling alphabet).
SPELLING = {
    "A": "Alfa", "B": "Bravo", "C": "Charlie", "D": "Delta", "E": "Echo", "F": "Foxtrot",
    "G": "Golf", "H": "Hotel", "I": "India", "J": "Juliett", "K": "Kilo", "L": "Lima",
    "M": "Mike", "N": "November", "O": "Oscar", "P": "Papa", "Q": "Quebec", "R": "Romeo",
    "S": "Sierra", "T": "Tango", "U": "Uniform", "V": "Victor", "W": "Whiskey", "X": "X-ray",
    "Y": "Yankee", "Z": "Zulu",
}  # fmt: skip
_HOSTILITY = {"FIENDE": "Fiende", "MISST": "Misstänkt", "OKAND": "Okänd"}
_CLASS_WORDS = {
    "tank": "stridsvagn",
    "armour": "pansarförband",
    "infantry_platoon": "infanteripluton",
    "uav": "drönare",
    "loitering_munition": "kringsvävande ammunition",
    "other": "okänt objekt",
}
_WORD_OF_ABBREVIATION = {CLASS_ABBREVIATIONS[k]: w for k, w in _CLASS_WORDS.items()}


def spell(text: str) -> str:
    """Digits as radio digit words and letters by the spelling alphabet, comma separated."""
    words = []
    for char in text:
        if char.isdigit():
            words.append(DIGIT_WORDS[int(char)])
        elif char in SPELLING:
            words.append(SPELLING[char])
    return ", ".join(words)


def announcement(cdm: Cdm) -> str:
    """The Swedish announcement of ``cdm``: type, number, hostility, class, position, course.

    The class is said in words when it is one of the built-in abbreviations, else spelled.
    """
    opening = "Nytt mål" if cdm.type == "MAL" else "Uppdatering mål"
    what = _WORD_OF_ABBREVIATION.get(cdm.class_abbreviation) or spell(cdm.class_abbreviation)
    zone_square, easting, northing = cdm.mgrs.split(" ")
    parts = [
        f"{opening}, nummer {spell(f'{cdm.number:04d}')}.",
        f"{_HOSTILITY.get(cdm.hostility, cdm.hostility)}, {what}.",
        f"Position {spell(zone_square)}. {spell(easting)}. {spell(northing)}.",
        f"Konfidens {spell(str(cdm.confidence_pct))} procent.",
    ]
    if cdm.course_deg is not None:
        parts.append(f"Kurs {spell(f'{cdm.course_deg:03d}')}.")
    if cdm.speed_kmh is not None:
        parts.append(f"Fart {spell(str(cdm.speed_kmh))} kilometer i timmen.")
    parts.append(f"Tid {spell(cdm.dtg[:6])} Zulu. Slut.")
    return " ".join(parts)
