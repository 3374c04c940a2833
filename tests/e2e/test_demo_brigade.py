"""``fischer-gateway demo`` as a newcomer runs it: the brigade operation's ten steps, told in order.

The demo runs to its end on its own (no ``--duration``) at eight times real speed, on free
loopback ports, with its stand-ins for every peer (gateway/sim/). Each of the operation's ten
steps is told once, numbered, in order, each with what confirmed it (for steps 6 to 10: what
the peer parsed of what it received over its wire); then the NFFI relay of a simulated
JAS 39, the cue held back near a friendly platoon, and the end. The gateway's JSON logs go
to a file, never between the story's lines. It says "deconfliction clear" or "NOT clear",
and never that an engagement is authorised.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(120)

#: What each step must say, and what its confirmation must say.
STEPS = [
    (
        r"blue force registered: 3 friendly units",
        r'"VIDAR \d" \(unauthenticated CoT callsign, source atak\), uid "BLUE-\dPLUT", at 34W E',
    ),
    (
        r"GUTE II battery registered: GUTE-1 at 34W EU 3178 0041, effectors EW_COUNTERMEASURES",
        r"confirmed: the GUTE II stand-in listens at https://127\.0\.0\.1:\d+/gute2/handoffs",
    ),
    (
        r"detections of inbound munitions ingested: F26E-00\d (EO|IR) sees loitering_munition"
        r" LANCET-3",
        r"confirmed: the gateway parsed it from F26E-00\d's MAVLink 2 stream",
    ),
    (
        r"fused track: track (?P<track>T-\S+) loitering_munition LANCET-3, confidence 0\.95"
        r" from EO\+IR",
        r"confirmed: the fusion processor published it",
    ),
    (
        r'deconfliction: clear for track {track}: nearest blue "VIDAR \d" \(unauthenticated CoT'
        r" callsign, source atak\) at \d+ m",
        r"confirmed: the counter-UAS processor considered \d+ friendly units",
    ),
    (
        r"GUTE II cue: HO-{track}-GUTE-1 revision \d+: track {track} to battery GUTE-1 \(\d+ m"
        r" from it, bearing \d{{3}}°\), recommended effector (TRIDON_MK2_40MM|TRACKFIRE_30MM);"
        r" the battery's operator decides",
        r"confirmed: GUTE II battery GUTE-1 received it over HTTPS: deconfliction clear,"
        r" recommended (TRIDON_MK2_40MM|TRACKFIRE_30MM), operator_authorisation_required true",
    ),
    (
        r"SLB JC3IEDM object published: object item fg:track:{track} to SLB over HTTPS",
        r"confirmed: SLB parsed fischer-gateway/slb-object-item/1: category MA, .*hostility HO",
    ),
    (
        r"SWECCIS FAS document dispatched: Intel document \S+ to SWECCIS over TLS",
        r'confirmed: SWECCIS \(client "demo-node"\) acknowledged it and parsed track {track}'
        r" \w+: loitering_munition LANCET-3 hostile",
    ),
    (
        r"Ra 180 CDM broadcast: new target NR \d{{4}} \(track {track}\) to the Ra 180 net over"
        r" UDP: MAL FIENDE LUFT-MUN POS ",
        r"confirmed: the radio gateway parsed MAL FIENDE LUFT-MUN at \d\d[C-X][A-Z]{{2}} ",
    ),
    (
        r"ATAK CoT: CoT fischer-trk-{track} type a-h-A-\S+ to ATAK over UDP",
        r"confirmed: ATAK parsed type a-h-A-\S+, APP-6D \(2525D\) symbol code \d{{20}} \(2525C"
        r" SHAP\S+\)",
    ),
]


@dataclass
class Run:
    lines: list[str]
    stderr: str
    log: Path


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Run:
    archive = tmp_path_factory.mktemp("demo") / "archive.jsonl"
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "demo", "--speed", "8", "--udp-port", "0",
         "--health-port", "0", "--archive", str(archive)],
        capture_output=True,
        text=True,
        timeout=100,
        check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert archive.stat().st_size > 0
    return Run(result.stdout.splitlines(), result.stderr, archive.parent / "gateway.log")


def at(lines: list[str], pattern: str, start: int = 0) -> int:
    for number in range(start, len(lines)):
        if re.search(pattern, lines[number]):
            return number
    raise AssertionError(f"no line from {start} matches {pattern!r}:\n" + "\n".join(lines))


def test_the_ten_steps_are_told_once_in_order_each_confirmed(demo: Run) -> None:
    lines = demo.lines
    numbered = [line for line in lines if re.match(r"\S+Z \[\d+/10\] ", line)]
    assert [re.search(r"\[(\d+)/10\]", line)[1] for line in numbered] == [  # type: ignore[index]
        str(n) for n in range(1, 11)
    ]
    track = ""
    previous = -1
    for number, (step, confirmation) in enumerate(STEPS, start=1):
        head = at(lines, rf"^\S+Z \[{number}/10\] " + step.format(track=re.escape(track)))
        assert head > previous
        match = re.search(r"track (T-\S+) ", lines[head])
        track = track or (match[1] if match else "")
        following = lines[head + 1 : (at(lines, r"^\S+Z ", head + 1))]
        assert any(
            re.search(confirmation.format(track=re.escape(track)), line) for line in following
        ), f"step {number} unconfirmed:\n" + "\n".join(lines[head : head + 6])
        previous = head


def test_the_voice_step_says_what_became_of_the_swedish_announcement(demo: Run) -> None:
    radio = at(demo.lines, r"\[9/10\] ")
    voice = at(demo.lines, r"^ +voice: ", radio)
    assert re.search(
        r"voice: (Swedish announcement \S+-NR\d{4}-MAL\.wav, [\d.]+ s at \d+ Hz \(espeak-ng\)"
        r"|espeak-ng is not installed, so no Swedish WAV \(text only\))",
        demo.lines[voice],
    )


def test_after_the_ten_steps_the_jas39_is_relayed_and_a_cue_is_held_back(demo: Run) -> None:
    last = at(demo.lines, r"\[10/10\] ")
    relay = at(demo.lines, r'NFFI relay: JAS 39 "GRIPEN 21" sent its track as NFFI 1\.3', last)
    assert re.search(
        r'confirmed: ATAK parsed a friendly a-f-A-\S+ "GRIPEN-21" uid SWE\.JAS39\.F21\.GRIPEN-21'
        r" \(Blue force relay \(NFFI, authenticated\)\)",
        demo.lines[relay + 1],
    )
    held = at(
        demo.lines,
        r'deconfliction NOT clear for track T-\S+: nearest blue "VIDAR 1" \(unauthenticated CoT'
        r" callsign, source atak\) at \d+ m",
        last,
    )
    assert "recommended effector none (deconfliction not clear)" in demo.lines[held + 1]
    assert "received revision" in demo.lines[held + 2]
    assert "recommended none" in demo.lines[held + 2]
    at(demo.lines, r"scenario complete; stopping \(logs in .*gateway\.log\)", held)
    assert not any("not confirmed" in line for line in demo.lines)


def test_the_logs_go_to_their_file_not_between_the_story(demo: Run) -> None:
    assert demo.stderr == ""
    assert not any(line.lstrip().startswith("{") for line in demo.lines)
    records = [json.loads(line) for line in demo.log.read_text().splitlines()]
    assert any(r["event"] == "gateway_started" for r in records)
    at(demo.lines, rf"the gateway's JSON logs: {re.escape(str(demo.log))}")


def test_the_demo_never_says_an_engagement_is_authorised(demo: Run) -> None:
    text = "\n".join(demo.lines).lower()
    assert "authorised" not in text.replace("operator_authorisation_required true", "")
    assert "engag" not in text
    assert "operator_authorisation_required true" in text
    assert "the battery's operator decides" in text


def test_a_reader_that_stops_early_ends_the_demo_quietly(tmp_path: Path) -> None:
    """``fischer-gateway demo | head -3``: the demo stops instead of playing to nobody."""
    with subprocess.Popen(
        [sys.executable, "-m", "gateway", "demo", "--speed", "8", "--udp-port", "0",
         "--health-port", "0", "--archive", str(tmp_path / "archive.jsonl")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    ) as process:  # fmt: skip
        assert process.stdout is not None
        first = process.stdout.readline()
        process.stdout.close()  # the reader goes; the next story line meets a broken pipe
        _, errors = process.communicate(timeout=100)
    assert b"scenario brigade" in first
    assert process.returncode == 0, errors
    assert errors == b""


def test_the_demo_says_where_its_live_map_listens(demo: Run) -> None:
    (line,) = [line for line in demo.lines if "the live map: " in line]
    assert re.search(r"the live map: http://127\.0\.0\.1:\d+/", line), line
