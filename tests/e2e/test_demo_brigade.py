"""``fischer-gateway demo`` as a newcomer runs it: the brigade operation, told step by step.

The demo runs to its end on its own (no ``--duration``) at eight times real speed, on free
loopback ports, and must tell each step of the operation in order, from real events: friendly
units and the battery registered, detections ingested, a track fused to 0.95 from EO and IR,
deconfliction with the nearest friendly unit, the GUTE II cue with its effector, then what the
battery and the ATAK stand-in received. It says "deconfliction clear" or "NOT clear", and
never that an engagement is authorised.
"""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

pytestmark = pytest.mark.timeout(90)


@pytest.fixture(scope="module")
def story(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    archive = tmp_path_factory.mktemp("demo") / "archive.jsonl"
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "demo", "--speed", "8", "--udp-port", "0",
         "--health-port", "0", "--archive", str(archive)],
        capture_output=True,
        text=True,
        timeout=80,
        check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert archive.stat().st_size > 0
    return result.stdout.splitlines()


def first(lines: list[str], pattern: str) -> int:
    for number, line in enumerate(lines):
        if re.search(pattern, line):
            return number
    raise AssertionError(f"no line matches {pattern!r}:\n" + "\n".join(lines[:60]))


def test_the_steps_come_in_the_operations_order(story: list[str]) -> None:
    steps = [
        r"battery registered: GUTE II GUTE-1 at 65\.8235 N 21\.6955 E",
        r'blue force registered: "VIDAR \d" \(unauthenticated CoT callsign, source atak\),'
        r' uid "BLUE-\dPLUT", at 34W E',
        r"detection ingested: F26E-00\d (EO|IR) sees loitering_munition LANCET-3",
        # Confirmed after M of N detections, a track may be published fused from the start.
        r"track T-\w+-\d+ (created|fused): loitering_munition LANCET-3 confidence 0\.95 .*"
        r" from EO\+IR",
        r'deconfliction clear for track T-\S+: nearest blue "VIDAR \d"'
        r" \(unauthenticated CoT callsign, source atak\) at \d+ m",
        r"GUTE II cue: track T-\S+ to battery GUTE-1 \(\d+ m from it, bearing \d{3}°\), recommended"
        r" effector (TRIDON_MK2_40MM|TRACKFIRE_30MM)",
        r"published: GUTE II battery GUTE-1 received cue HO-T-\S+ revision 0 over HTTPS",
    ]
    at = [first(story, step) for step in steps]
    assert at[0] < at[2], at
    # The story sink's lines come in the bus's order; the battery's receipt is told by the
    # battery, concurrently with the story sink's write, so it may come just before its cue.
    assert at[1] < at[3] < at[4] < at[5], at
    first(story, r"published: CoT to ATAK \(udp 127\.0\.0\.1:\d+\) fischer-trk-T-\S+ a-h-A")
    first(story, r"track T-\S+ created: tank T-72B3")
    first(story, r"scenario complete; stopping")


def test_the_lancet_passing_vidar_1_is_told_not_clear_with_no_effector(story: list[str]) -> None:
    held = first(
        story,
        r'deconfliction NOT clear for track T-\S+: nearest blue "VIDAR 1"'
        r" \(unauthenticated CoT callsign, source atak\) at \d+ m",
    )
    assert "recommended effector none (deconfliction not clear)" in story[held + 1]
    received = first(
        story, r"received cue HO-T-\S+ revision [1-9]\d* over HTTPS: deconfliction NOT"
    )
    assert "recommended none" in story[received]


def test_the_demo_never_says_an_engagement_is_authorised(story: list[str]) -> None:
    text = "\n".join(story).lower()
    assert "authorised" not in text.replace("operator_authorisation_required true", "")
    assert "engag" not in text
    assert "operator_authorisation_required true" in text
    assert "the battery's operator decides" in text
