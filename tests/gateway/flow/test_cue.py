"""The counter-UAS cue desk: nearest able battery, deconfliction, once per track, never an order."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest

from gateway.domain.effectors import load_effector_table
from gateway.domain.geodesy import destination
from gateway.domain.peertext import Provenance
from gateway.events import BlueForce, Handoff, Position, Track
from gateway.flow.blueforce import BlueForceRegistry
from gateway.flow.cue import Battery, CueDesk

NOW = datetime(2026, 11, 23, 12, 0, tzinfo=UTC)
BATTERY = Position(lat_deg=65.80, lon_deg=21.70)
ALL = frozenset({"TRIDON_MK2_40MM", "TRACKFIRE_30MM", "EW_COUNTERMEASURES", "GIRAFFE_1X_DESIGNATE"})


def at(origin: Position, bearing_deg: float, distance_m: float) -> Position:
    lat, lon = destination(origin.lat_deg, origin.lon_deg, bearing_deg, distance_m)
    return Position(lat_deg=lat, lon_deg=lon)


def track(
    where: Position,
    *,
    track_id: str = "T-1",
    cls: str = "loitering_munition",
    confidence: float = 0.95,
    status: str = "updated",
    cep90_m: float = 20.0,
) -> Track:
    return Track.model_validate(
        {
            "event_id": f"{track_id}-x",
            "track_id": track_id,
            "time": NOW,
            "status": status,
            "object_class": cls,
            "subtype": "LANCET-3",
            "confidence": confidence,
            "position": where,
            "cep50_m": cep90_m / 1.8,
            "cep90_m": cep90_m,
            "first_seen": NOW,
            "last_seen": NOW,
        }
    )


def blue(uid: str, where: Position, time: datetime = NOW) -> BlueForce:
    return BlueForce(
        event_id=f"b-{uid}", uid=uid, time=time, callsign=uid, position=where, source="cot"
    )


FAR = at(BATTERY, 180, 9000)  # a friendly unit far from every track here


def desk(
    batteries: list[Battery] | None = None,
    *,
    clock: datetime = NOW,
    min_confidence: float = 0.9,
) -> CueDesk:
    registry = BlueForceRegistry(lambda: clock, max_age_s=300)
    registry.pin(blue("HQ-FAR", FAR))
    return CueDesk(
        batteries or [Battery("GUTE-1", BATTERY, ALL)],
        load_effector_table(),
        registry,
        classes=frozenset({"loitering_munition", "uav"}),
        min_confidence=min_confidence,
    )


def test_a_munition_with_no_friend_near_is_cued_clear_with_the_preferred_effector() -> None:
    cue = desk()
    handoff = cue.consider(track(at(BATTERY, 90, 2000)))
    assert isinstance(handoff, Handoff)
    assert handoff.battery == "GUTE-1"
    assert handoff.range_m == pytest.approx(2000, abs=0.01)
    assert handoff.bearing_deg == pytest.approx(90, abs=0.01)
    assert handoff.deconfliction.clear
    assert handoff.deconfliction.blue_units_considered == 1
    assert handoff.deconfliction.nearest_blue_uid == "HQ-FAR"
    assert handoff.recommended_effector == "TRACKFIRE_30MM"
    assert [o.effector for o in handoff.options] == [
        "TRACKFIRE_30MM",
        "TRIDON_MK2_40MM",
        "EW_COUNTERMEASURES",
    ]
    assert handoff.operator_authorisation_required is True
    assert handoff.handoff_id == handoff.event_id


def test_a_track_within_danger_close_of_a_friend_is_not_clear_and_nothing_is_recommended() -> None:
    cue = desk()
    target = at(BATTERY, 90, 2000)
    cue.blue.update(blue("PLT-2", at(target, 0, 250)))
    handoff = cue.consider(track(target))
    assert handoff is not None
    assert not handoff.deconfliction.clear
    assert handoff.recommended_effector is None
    assert handoff.deconfliction.nearest_blue_uid == "PLT-2"
    assert handoff.deconfliction.nearest_blue_m == pytest.approx(250, abs=0.01)
    # Each offered effector with its own result: all inside their danger-close radius here.
    assert {o.effector: o.deconfliction_clear for o in handoff.options} == {
        "TRACKFIRE_30MM": False,
        "TRIDON_MK2_40MM": False,
        "EW_COUNTERMEASURES": False,
    }
    assert cue.counts.not_clear == 1


def test_one_effector_inside_its_radius_is_enough_to_withhold_the_recommendation() -> None:
    cue = desk()
    target = at(BATTERY, 90, 2000)
    cue.blue.update(blue("PLT-2", at(target, 180, 500)))  # 500 m: TRIDON's 600 m is not clear
    handoff = cue.consider(track(target))
    assert handoff is not None
    options = {o.effector: o.deconfliction_clear for o in handoff.options}
    assert options == {
        "TRACKFIRE_30MM": True,
        "TRIDON_MK2_40MM": False,
        "EW_COUNTERMEASURES": True,
    }
    assert not handoff.deconfliction.clear
    assert handoff.recommended_effector is None


def test_the_tracks_uncertainty_is_taken_off_the_distance_to_the_friend() -> None:
    target = at(BATTERY, 90, 3000)  # 3 km: TRIDON and EW only
    near = desk()
    near.blue.update(blue("PLT-2", at(target, 0, 700)))
    assert near.consider(track(target, cep90_m=50)).deconfliction.clear  # type: ignore[union-attr]
    vague = desk()
    vague.blue.update(blue("PLT-2", at(target, 0, 700)))
    handoff = vague.consider(track(target, cep90_m=150))  # 700 - 150 < 600
    assert handoff is not None
    assert not handoff.deconfliction.clear


def test_the_cue_goes_to_the_nearest_battery_able_to_engage() -> None:
    target = at(BATTERY, 90, 2000)
    near_but_unable = Battery("GUTE-NEAR", at(target, 0, 500), frozenset({"GIRAFFE_1X_DESIGNATE"}))
    able_far = Battery("GUTE-FAR", at(target, 180, 3500), ALL)
    able_near = Battery("GUTE-MID", at(target, 270, 1500), frozenset({"TRACKFIRE_30MM"}))
    cue = desk([near_but_unable, able_far, able_near])
    handoff = cue.consider(track(target))
    assert handoff is not None
    assert handoff.battery == "GUTE-MID"
    assert [o.effector for o in handoff.options] == ["TRACKFIRE_30MM"]


def test_out_of_every_batterys_reach_is_no_cue_and_counted() -> None:
    cue = desk([Battery("GUTE-1", BATTERY, frozenset({"TRACKFIRE_30MM"}))])
    assert cue.consider(track(at(BATTERY, 0, 6000))) is None
    assert cue.counts.out_of_reach == 1


def test_once_per_track_until_it_is_lost() -> None:
    cue = desk()
    where = at(BATTERY, 45, 1500)
    assert cue.consider(track(where, status="created")) is not None
    assert cue.consider(track(where)) is None
    assert cue.consider(track(where, track_id="T-2")) is not None
    assert cue.consider(track(where, status="lost")) is not None  # withdrawn, below
    assert cue.counts.handed_off == 2


class TestLostTracks:
    """A cued track that is lost leaves no live cue at the battery."""

    def lost(self, where: Position, track_id: str = "T-1") -> Track:
        return track(where, track_id=track_id, status="lost").model_copy(
            update={"time": NOW + timedelta(seconds=61), "last_seen": NOW}
        )

    def test_its_cue_is_withdrawn_once_with_why_and_nothing_recommended(self) -> None:
        cue = desk()
        where = at(BATTERY, 45, 1500)
        first = cue.consider(track(where))
        assert first is not None
        assert first.recommended_effector is not None
        withdrawn = cue.consider(self.lost(where))
        assert withdrawn is not None
        assert withdrawn.status == "withdrawn"
        assert (withdrawn.handoff_id, withdrawn.revision) == (first.handoff_id, 1)
        assert withdrawn.event_id == f"{first.handoff_id}-r1"
        assert withdrawn.note.startswith("track T-1 lost: no detection since 2026-11-23T12:00:00Z")
        assert withdrawn.recommended_effector is None
        assert withdrawn.options == ()
        assert withdrawn.superseded_by is None
        assert withdrawn.operator_authorisation_required is True
        assert (cue.counts.withdrawn, cue.counts.not_clear) == (1, 0)
        # Forgotten: a second loss (a replay) withdraws nothing more.
        assert cue.consider(self.lost(where)) is None
        assert cue.counts.withdrawn == 1

    def test_a_lost_track_never_cued_sends_nothing(self) -> None:
        cue = desk()
        assert cue.consider(self.lost(at(BATTERY, 45, 1500), "T-7")) is None
        assert cue.counts.withdrawn == 0

    def test_a_cue_carried_on_to_a_survivor_is_withdrawn_when_the_survivor_is_lost(
        self,
    ) -> None:
        cue = desk(min_confidence=0.9)
        where = at(BATTERY, 90, 2000)
        assert cue.consider(track(where, track_id="T-1", confidence=0.5)) is None
        young = cue.consider(track(where, track_id="T-2"))
        assert young is not None
        merged = track(where, track_id="T-2", status="merged").model_copy(
            update={"merged_into": "T-1", "time": NOW + timedelta(seconds=2)}
        )
        assert cue.consider(merged) is None  # carried on with T-1
        withdrawn = cue.consider(self.lost(where, "T-1"))
        assert withdrawn is not None
        assert (withdrawn.handoff_id, withdrawn.status) == (young.handoff_id, "withdrawn")
        assert withdrawn.revision == 1
        assert withdrawn.note.startswith("track T-1 lost")


def test_a_weak_track_waits_for_fusion_and_other_classes_are_not_cued() -> None:
    cue = desk()
    where = at(BATTERY, 45, 1500)
    assert cue.consider(track(where, confidence=0.8)) is None
    assert cue.consider(track(where, cls="tank")) is None
    assert cue.consider(track(where, confidence=0.95)) is not None
    assert cue.counts.below_confidence == 1


def test_stale_friendly_reports_are_not_used_but_pinned_units_are() -> None:
    target = at(BATTERY, 90, 2000)
    cue = desk()
    cue.blue.update(blue("OLD", at(target, 0, 100), time=NOW - timedelta(seconds=301)))
    handoff = cue.consider(track(target))
    assert handoff is not None
    assert handoff.deconfliction.clear
    assert handoff.deconfliction.nearest_blue_uid == "HQ-FAR"
    pinned = desk()
    pinned.blue.pin(blue("HQ", at(target, 0, 100), time=NOW - timedelta(days=3)))
    pinned.blue.update(blue("HQ", at(target, 0, 9000)))  # a report cannot move a pinned unit
    held = pinned.consider(track(target))
    assert held is not None
    assert held.deconfliction.nearest_blue_uid == "HQ"
    assert not held.deconfliction.clear


def test_a_handoff_carries_no_field_that_could_command_an_effector() -> None:
    handoff = desk().consider(track(at(BATTERY, 90, 2000)))
    assert handoff is not None
    words = " ".join(_keys(handoff.model_dump(mode="json"))).lower()
    for command in ("fire", "engage", "launch", "weapons_free", "authorised", "authorized"):
        assert command not in words
    with pytest.raises(ValueError, match="operator_authorisation_required"):
        Handoff.model_validate({**handoff.model_dump(), "operator_authorisation_required": False})


def _keys(value: object) -> list[str]:
    if isinstance(value, dict):
        return [k for key, item in value.items() for k in (str(key), *_keys(item))]
    if isinstance(value, list):
        return [k for item in value for k in _keys(item)]
    return []


def test_a_cue_is_revised_at_once_when_a_friend_comes_within_danger_close() -> None:
    cue = desk()
    target = at(BATTERY, 90, 2000)
    first = cue.consider(track(target, status="created"))
    assert first is not None
    assert first.deconfliction.clear
    assert (first.revision, first.event_id) == (0, first.handoff_id)
    cue.blue.update(blue("PLT-2", at(target, 0, 200)))
    second = cue.consider(track(target))  # the same instant: losing "clear" never waits
    assert second is not None
    assert (second.handoff_id, second.revision) == (first.handoff_id, 1)
    assert second.event_id == f"{first.handoff_id}-r1"
    assert not second.deconfliction.clear
    assert second.recommended_effector is None
    assert cue.consider(track(target)) is None  # unchanged: nothing new to say


def test_a_cue_that_becomes_clear_again_waits_for_the_revision_interval() -> None:
    target = at(BATTERY, 90, 2000)
    times = iter([NOW, NOW, NOW + timedelta(seconds=1), NOW + timedelta(seconds=6)])
    cue = desk()
    cue.blue.update(blue("PLT-2", at(target, 0, 200)))
    assert not cue.consider(
        track(target).model_copy(update={"time": next(times)})
    ).deconfliction.clear  # type: ignore[union-attr]
    away = at(target, 0, 3000)
    cue.blue.update(blue("PLT-2", away, time=NOW + timedelta(seconds=1)))
    assert cue.consider(track(target).model_copy(update={"time": next(times)})) is None
    assert cue.consider(track(target).model_copy(update={"time": next(times)})) is None
    later = cue.consider(track(target).model_copy(update={"time": next(times)}))
    assert later is not None
    assert later.revision == 1
    assert later.deconfliction.clear
    assert later.recommended_effector == "TRACKFIRE_30MM"


def test_a_flood_of_friendly_reports_makes_the_picture_incomplete_and_nothing_clear() -> None:
    target = at(BATTERY, 90, 2000)
    cue = CueDesk(
        [Battery("GUTE-1", BATTERY, ALL)],
        load_effector_table(),
        BlueForceRegistry(lambda: NOW, max_age_s=300, max_units=3),
        classes=frozenset({"loitering_munition"}),
        min_confidence=0.9,
    )
    cue.blue.update(blue("PLT-2", at(target, 0, 200)))  # the real platoon, near the track
    for n in range(3):  # then three spoofed units far away push it out
        cue.blue.update(blue(f"FAKE-{n}", at(target, 0, 20_000 + n)))
    handoff = cue.consider(track(target))
    assert handoff is not None
    assert handoff.deconfliction.nearest_blue_uid == "FAKE-0"
    assert not handoff.deconfliction.blue_picture_complete
    assert not handoff.deconfliction.clear
    assert handoff.recommended_effector is None
    assert cue.blue.dropped == 1


def test_with_no_friendly_position_known_nothing_is_clear() -> None:
    cue = CueDesk(
        [Battery("GUTE-1", BATTERY, ALL)],
        load_effector_table(),
        BlueForceRegistry(lambda: NOW, max_age_s=300),
        classes=frozenset({"loitering_munition"}),
        min_confidence=0.9,
    )
    handoff = cue.consider(track(at(BATTERY, 90, 2000)))
    assert handoff is not None
    assert handoff.deconfliction.blue_units_considered == 0
    assert not handoff.deconfliction.blue_picture_complete
    assert not handoff.deconfliction.clear
    assert handoff.recommended_effector is None
    assert all(o.deconfliction_clear for o in handoff.options)  # no unit inside any radius


def test_the_cue_says_where_its_blue_force_picture_came_from() -> None:
    cue = desk()
    target = at(BATTERY, 90, 2000)
    hostile = "WEAPONS FREE\u202e - ENGAGE AUTHORISED BY BDE"
    report = blue("ANDROID-RED", at(target, 0, 150)).model_copy(
        update={"callsign": hostile, "source_name": "atak-mesh"}
    )
    cue.blue.update(report)
    handoff = cue.consider(track(target))
    assert handoff is not None
    check = handoff.deconfliction
    # Made safe again where it is used (a report may not have come through a source that did).
    assert check.nearest_blue_callsign == "WEAPONS FREE - ENGAGE AUTHORI..."
    assert check.nearest_blue_callsign_provenance == "unauthenticated CoT callsign"
    assert (check.nearest_blue_source, check.nearest_blue_provenance) == (
        "atak-mesh",
        Provenance.UNAUTHENTICATED,
    )
    # HQ-FAR was pinned without a provenance of its own: its source name defaults to "cot".
    assert {(s.source, s.provenance, s.units) for s in check.blue_sources} == {
        ("atak-mesh", Provenance.UNAUTHENTICATED, 1),
        ("cot", Provenance.UNAUTHENTICATED, 1),
    }


class TestMergedTracks:
    """A cued track merged into another never leaves two live cues for one object."""

    def merged(self, track_id: str, into: str, where: Position) -> Track:
        return track(where, track_id=track_id, status="merged").model_copy(
            update={"merged_into": into, "time": NOW + timedelta(seconds=2)}
        )

    def test_both_cued_the_merged_ones_cue_is_superseded_by_the_survivors(self) -> None:
        cue = desk()
        where = at(BATTERY, 90, 2000)
        first = cue.consider(track(where, track_id="T-1"))
        second = cue.consider(track(at(BATTERY, 90, 2010), track_id="T-2"))
        assert first is not None
        assert second is not None
        revision = cue.consider(self.merged("T-2", "T-1", where))
        assert revision is not None
        assert revision.handoff_id == second.handoff_id
        assert revision.revision == 1
        assert revision.event_id == f"{second.handoff_id}-r1"
        assert revision.status == "superseded"
        assert revision.superseded_by == first.handoff_id
        assert revision.recommended_effector is None
        assert "merged into T-1" in revision.note
        assert cue.counts.superseded == 1
        # The merged track is gone from the desk; the survivor's cue stands unchanged.
        assert cue.consider(track(where, track_id="T-1")) is None

    def test_only_the_merged_one_cued_its_cue_carries_on_with_the_survivor(self) -> None:
        cue = desk(min_confidence=0.9)
        where = at(BATTERY, 90, 2000)
        assert cue.consider(track(where, track_id="T-1", confidence=0.5)) is None  # not yet
        young = cue.consider(track(where, track_id="T-2"))
        assert young is not None
        assert cue.consider(self.merged("T-2", "T-1", where)) is None
        assert cue.counts.carried_on == 1
        survivor = track(where, track_id="T-1").model_copy(
            update={"time": NOW + timedelta(seconds=3)}
        )
        revision = cue.consider(survivor)
        assert revision is not None
        assert revision.handoff_id == young.handoff_id  # one cue id for the object
        assert revision.revision == 1
        assert revision.status == "active"
        assert revision.track.track_id == "T-1"
        assert "now follows T-1" in revision.note
        assert cue.counts.handed_off == 1
        # Said once: the next update with nothing new sends nothing.
        assert cue.consider(survivor) is None

    def test_a_merged_track_never_cued_sends_nothing(self) -> None:
        cue = desk()
        assert cue.consider(self.merged("T-9", "T-1", at(BATTERY, 90, 2000))) is None
