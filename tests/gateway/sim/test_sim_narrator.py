"""The demo's narrator tells the ten steps once each, in order, whatever order wires answer in."""

from __future__ import annotations

import re
from pathlib import Path

from gateway.contract import sample_events
from gateway.domain.geodesy import to_mgrs
from gateway.events import BlueForce, Detection, EventKind, Handoff, Position, Sensor
from gateway.sim.atak import CotSeen
from gateway.sim.narrator import Narrator
from gateway.sim.ra180 import Heard, Wav, read_cdm
from gateway.sim.slb import SlbItem
from gateway.sim.sweccis import FasTrack

LAT, LON = 65.84, 21.70
#: A new-target message; ``mgrs`` is filled in with the track's position.
CDM = "MAL FIENDE LUFT-MUN POS {mgrs} KONF 095 TID 270514ZNOV26 NR 0004"


def samples() -> tuple[Detection, BlueForce, Handoff]:
    detection, blue, handoff = sample_events(
        frozenset({EventKind.DETECTION, EventKind.BLUE_FORCE, EventKind.HANDOFF})
    )
    assert isinstance(detection, Detection)
    assert isinstance(blue, BlueForce)
    assert isinstance(handoff, Handoff)
    munition = detection.model_copy(update={"object_class": "loitering_munition"})
    track = handoff.track.model_copy(
        update={
            "object_class": "loitering_munition",
            "sensors": (Sensor.EO, Sensor.IR),
            "position": Position(lat_deg=LAT, lon_deg=LON),
        }
    )
    return munition, blue, handoff.model_copy(update={"track": track})


def told(lines: list[str]) -> list[int]:
    return [int(m[1]) for line in lines if (m := re.search(r"Z \[(\d+)/10\] ", line))]


def test_steps_wait_for_their_predecessors_and_are_told_once(tmp_path: Path) -> None:
    lines: list[str] = []
    narrator = Narrator(lines.append, blue_units=1, voice=True)
    munition, blue, handoff = samples()
    track_id = handoff.track.track_id
    mgrs = to_mgrs(LAT, LON, 10, spaced=True).replace(" ", "", 1)
    cdm = read_cdm(CDM.format(mgrs=mgrs))
    assert cdm is not None
    # The far end answers first: ATAK, the radio net, SWECCIS, SLB, the battery.
    narrator.cot(
        CotSeen(f"fischer-trk-{track_id}", "a-h-A-M-F-Q-A", "m-f", str(LAT), str(LON), "40",
                "T", "", "SHAPMFQA-------", "10060100001103000100")
    )  # fmt: skip
    wav = Wav(tmp_path / "x-NR0004-MAL.wav", 3.0, 22050)
    narrator.heard(Heard(CDM.format(mgrs=mgrs), cdm, wav))
    narrator.fas_track(
        FasTrack("d1", "node", track_id, "created", "loitering_munition", "LANCET-3",
                 "hostile", "0.95", str(LAT), str(LON))
    )  # fmt: skip
    narrator.slb_item(
        SlbItem("s", "e", f"fg:track:{track_id}", "MA", "L", "HO", LAT, LON, track_id)
    )
    narrator.cue_received(
        {"handoff_id": handoff.handoff_id, "revision": handoff.revision, "deconfliction": {}}
    )
    assert told(lines) == []
    narrator.event(handoff)  # the featured track, but no friendly unit nor detection yet
    narrator.event(munition)
    assert told(lines) == []
    narrator.battery("GUTE-1", Position(lat_deg=LAT, lon_deg=LON), ["TRIDON_MK2_40MM"], "u")
    narrator.event(blue)
    assert told(lines) == list(range(1, 11))
    narrator.event(blue)
    narrator.event(handoff)
    assert told(lines) == list(range(1, 11))
    assert narrator.missing() == []
    assert any("x-NR0004-MAL.wav, 3.0 s at 22050 Hz" in line for line in lines)


def test_what_is_never_confirmed_is_listed_as_missing() -> None:
    lines: list[str] = []
    narrator = Narrator(lines.append, blue_units=3, voice=False)
    munition, blue, handoff = samples()
    narrator.event(blue)
    narrator.battery("GUTE-1", Position(lat_deg=LAT, lon_deg=LON), ["TRIDON_MK2_40MM"], "u")
    narrator.event(munition)
    assert told(lines) == []  # waiting for the other two platoons, or a cued track
    narrator.event(handoff)
    assert told(lines) == [1, 2, 3, 4, 5]
    assert narrator.missing()[0] == "[6] GUTE II cue"
