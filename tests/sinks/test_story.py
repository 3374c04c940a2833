"""The console's story format: the operation's steps, once each, never "engagement authorised"."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from gateway.contract import sample_events
from gateway.events import (
    BlueForce,
    Deconfliction,
    Detection,
    EventKind,
    Handoff,
    Position,
    Provenance,
    Sensor,
    Track,
)
from sinks._story import Story
from sinks.console import describe

T = datetime(2026, 11, 23, 12, 0, tzinfo=UTC)
WHERE = Position(lat_deg=65.8252, lon_deg=21.6886)


def detection(n: int, airframe: str = "F26E-001", sensor: Sensor = Sensor.EO) -> Detection:
    return Detection(
        event_id=f"d{n}",
        airframe=airframe,
        time=T,
        sensor=sensor,
        object_class="loitering_munition",
        subtype="LANCET-3",
        confidence=0.8,
        position=WHERE,
        sigma_h_m=12.0,
    )


def test_the_first_detection_per_airframe_sensor_and_class_is_told_then_only_counted() -> None:
    story = Story()
    first = story.tell(detection(1))
    assert first == [
        "detection ingested: F26E-001 EO sees loitering_munition LANCET-3 conf 0.80"
        " at 34W EU 3146 0059 ±12 m"
    ]
    assert story.tell(detection(2)) == []
    assert len(story.tell(detection(3, "F26E-002", Sensor.IR))) == 1


def test_tracks_are_told_when_their_fused_picture_changes_and_when_lost() -> None:
    story = Story()
    base = sample_events(frozenset({EventKind.TRACK}))[0]
    assert isinstance(base, Track)
    created = base.model_copy(update={"status": "created", "sensors": (Sensor.EO,)})
    fused = base.model_copy(
        update={"confidence": 0.95, "sensors": (Sensor.EO, Sensor.IR), "airframes": ("A", "B")}
    )
    (line,) = story.tell(created)
    assert line.startswith("track T1 created: uav confidence 0.80")
    (line,) = story.tell(fused)
    assert "track T1 fused: uav confidence 0.95" in line
    assert "from EO+IR of A, B" in line
    assert story.tell(fused.model_copy(update={"event_id": "again"})) == []
    (line,) = story.tell(base.model_copy(update={"status": "lost"}))
    assert line.startswith("track T1 lost")


def test_a_track_lost_within_a_second_of_its_last_detection_says_how_long_it_was_silent() -> None:
    """The line is stamped to the second: "no detection since <that second>" read as nonsense."""
    base = sample_events(frozenset({EventKind.TRACK}))[0]
    assert isinstance(base, Track)
    lost = base.model_copy(
        update={"status": "lost", "time": base.last_seen + timedelta(milliseconds=600)}
    )
    (line,) = Story().tell(lost)
    last = base.last_seen.astimezone(UTC).strftime("%H:%M:%S.%f")[:-5]
    assert line == f"track T1 lost: no detection for 0.6 s (the last at {last}Z)"


def test_a_merged_track_is_told_as_merged_and_its_superseded_cue_as_such() -> None:
    story = Story()
    base = sample_events(frozenset({EventKind.TRACK}))[0]
    assert isinstance(base, Track)
    (line,) = story.tell(base.model_copy(update={"status": "merged", "merged_into": "T0"}))
    assert line == "track T1 merged into T0: a second track of the same object"
    assert "lost" not in line
    sample = sample_events(frozenset({EventKind.HANDOFF}))[0]
    assert isinstance(sample, Handoff)
    superseded = sample.model_copy(
        update={"revision": 1, "status": "superseded", "superseded_by": "HO-T0-GUTE-1",
                "note": "track T1 merged into T0", "recommended_effector": None}
    )  # fmt: skip
    (line,) = story.tell(superseded)
    assert line.startswith(f"GUTE II cue {sample.handoff_id} revision 1 superseded at battery")
    assert line.endswith("by HO-T0-GUTE-1: track T1 merged into T0")


def test_a_withdrawn_cue_is_told_as_withdrawn_with_why() -> None:
    sample = sample_events(frozenset({EventKind.HANDOFF}))[0]
    assert isinstance(sample, Handoff)
    note = "track T1 lost: no detection since 2026-11-22T12:00:00Z"
    withdrawn = sample.model_copy(
        update={"revision": 2, "status": "withdrawn", "note": note,
                "recommended_effector": None, "options": ()}
    )  # fmt: skip
    (line,) = Story().tell(withdrawn)
    assert line == f"GUTE II cue {sample.handoff_id} revision 2 withdrawn at battery GUTE-1: {note}"
    assert "recommended" not in line
    (text,) = [describe(withdrawn)]
    assert f"{sample.handoff_id} r2 WITHDRAWN (track T1)" in text
    assert text.endswith(note)
    assert "recommend" not in text


def test_a_cue_says_deconfliction_and_recommendation_and_leaves_the_decision_to_the_operator() -> (
    None
):
    story = Story()
    sample = sample_events(frozenset({EventKind.HANDOFF}))[0]
    assert isinstance(sample, Handoff)
    clear, cue = story.tell(sample)
    assert clear.startswith("deconfliction clear for track T1: no friendly unit known")
    assert "recommended effector TRACKFIRE_30MM; the battery's operator decides" in cue
    held = sample.model_copy(
        update={
            "recommended_effector": None,
            "deconfliction": Deconfliction(
                clear=False,
                nearest_blue_uid="PLT-2",
                nearest_blue_callsign="2. pluton",
                nearest_blue_m=250.0,
                blue_units_considered=3,
            ),
        }
    )
    not_clear, cue = story.tell(held)
    # A record without provenance (archived before it was kept) is never shown bare.
    assert not_clear.startswith(
        'deconfliction NOT clear for track T1: nearest blue "2. pluton"'
        " (callsign of unknown provenance) at 250 m"
    )
    assert "recommended effector none (deconfliction not clear)" in cue
    for line in (clear, not_clear, cue):
        assert "authorised" not in line
        assert "engage" not in line


def test_friendly_units_are_registered_once() -> None:
    story = Story()
    unit = BlueForce(event_id="b", uid="PLT-1", time=T, callsign="1. pluton", position=WHERE,
                     source="cot")  # fmt: skip
    assert story.tell(unit) == [
        'blue force registered: "1. pluton" (unauthenticated CoT callsign), uid "PLT-1",'
        " at 34W EU 3146 0059 via cot"
    ]
    assert story.tell(unit.model_copy(update={"event_id": "b2"})) == []


def test_a_callsign_from_an_unauthenticated_peer_is_shown_only_safe_and_marked() -> None:
    sample = sample_events(frozenset({EventKind.HANDOFF}))[0]
    assert isinstance(sample, Handoff)
    check = Deconfliction(
        clear=False,
        nearest_blue_uid="ANDROID-RED",
        nearest_blue_callsign="WEAPONS FREE\u202e - ENGAGE AUTHORISED BY BDE",
        nearest_blue_m=110.0,
        blue_units_considered=2,
        nearest_blue_callsign_provenance="unauthenticated CoT callsign",
        nearest_blue_source="atak-mesh",
        nearest_blue_provenance=Provenance.UNAUTHENTICATED,
    )
    held, _ = Story().tell(sample.model_copy(update={"deconfliction": check}))
    assert held.startswith(
        'deconfliction NOT clear for track T1: nearest blue "WEAPONS FREE - ENGAGE AUTHORI..."'
        " (unauthenticated CoT callsign, source atak-mesh) at 110 m"
    )
    # Without a callsign, the uid is shown with the provenance instead.
    bare = check.model_copy(update={"nearest_blue_callsign": None})
    held, _ = Story().tell(sample.model_copy(update={"deconfliction": bare}))
    assert 'nearest blue uid "ANDROID-RED" (unauthenticated, source atak-mesh) at 110 m' in held
