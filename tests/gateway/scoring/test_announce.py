"""Ra 180 "new target" messages traced to the track they announce, not to the nearest target."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from gateway.domain.geodesy import destination
from gateway.events import Position, Track
from gateway.scoring.announce import announced_tracks, announcements_by_track
from sinks.ra180.cdm import Cdm, compose

T0 = datetime(2026, 11, 27, 5, 0, tzinfo=UTC)
ORIGIN = (65.8450, 21.6600)


def track(track_id: str, east_m: float, *, seconds: float = 0.0) -> Track:
    lat, lon = destination(*ORIGIN, 90.0, east_m)
    time = T0 + timedelta(seconds=seconds)
    return Track(
        event_id=f"{track_id}-{seconds}",
        track_id=track_id,
        time=time,
        status="created" if seconds == 0 else "updated",
        object_class="armour",
        confidence=0.9,
        position=Position(lat_deg=lat, lon_deg=lon),
        cep50_m=8.0,
        cep90_m=15.0,
        first_seen=T0,
        last_seen=time,
        hostility="hostile",
    )


def cdm(event: Track, number: int, kind: str = "MAL") -> Cdm:
    return compose(event, message_type="MAL" if kind == "MAL" else "UPPD", number=number)


def test_a_message_is_traced_to_its_track_though_nearer_a_neighbour() -> None:
    # Vehicles A at 0 m and B at 30 m. Track 1 (of A) is first published 20 m east, nearer
    # B: the nearest-position count would give B two announcements and A none.
    first = track("T-1", 20.0)
    second = track("T-2", 31.0)
    events = [first, second, track("T-1", 2.0, seconds=5), track("T-2", 30.0, seconds=5)]
    heard = [cdm(first, 1), cdm(second, 2)]
    assert announced_tracks(heard, events) == {1: "T-1", 2: "T-2"}
    counted = announcements_by_track(heard, events, {"A": ["T-1"], "B": ["T-2"]}, ["A", "B"])
    assert counted.per_target == {"A": 1, "B": 1}
    assert (counted.untraced, counted.false_track) == (0, 0)


def test_two_tracks_in_one_grid_square_are_told_apart_by_the_numbers_updates() -> None:
    # Both first published in one 10 m square in the same minute: the MAL alone cannot say
    # whose it is; each number's later update can.
    one, two = track("T-1", 12.0), track("T-2", 13.0)
    later_one, later_two = track("T-1", 0.0, seconds=9), track("T-2", 30.0, seconds=9)
    events = [one, two, later_one, later_two]
    assert cdm(one, 7).mgrs == cdm(two, 8).mgrs
    heard = [cdm(one, 7), cdm(two, 8), cdm(later_one, 7, "UPPD"), cdm(later_two, 8, "UPPD")]
    assert announced_tracks(heard, events) == {7: "T-1", 8: "T-2"}
    # Without the updates, neither is traced: counted as such, never guessed.
    counted = announcements_by_track(heard[:2], events, {"A": ["T-1"], "B": ["T-2"]}, "AB")
    assert counted.per_target == {"A": 0, "B": 0}
    assert counted.untraced == 2


def test_a_double_announcement_and_a_false_track_are_counted_as_what_they_are() -> None:
    a1, a2, ghost = track("T-1", 0.0), track("T-3", 60.0), track("T-9", 500.0)
    events = [a1, a2, ghost]
    heard = [cdm(a1, 1), cdm(a2, 2), cdm(ghost, 3)]
    counted = announcements_by_track(heard, events, {"A": ["T-1", "T-3"]}, ["A", "B"])
    assert counted.per_target == {"A": 2, "B": 0}  # two tracks of A: announced twice
    assert counted.false_track == 1  # T-9 matched no target


def test_a_message_whose_event_is_not_in_the_archive_is_passed_over() -> None:
    first = track("T-1", 0.0)
    unarchived = track("T-1", 40.0, seconds=70)  # the run stopped before it was written
    heard = [cdm(first, 1), cdm(unarchived, 1, "UPPD")]
    assert announced_tracks(heard, [first]) == {1: "T-1"}
    assert announced_tracks([cdm(unarchived, 4)], [first]) == {4: None}


def test_a_track_traced_to_one_number_is_no_candidate_of_another() -> None:
    # Seen on parked-vehicles: number 3's MAL (T-3, as created) shares its square and
    # minute with later updates of T-5, which number 5's own MAL traces; so 3 is T-3's.
    created = track("T-3", 12.0)
    t5_early, t5_there = track("T-5", 40.0), track("T-5", 13.0, seconds=8)
    events = [created, t5_early, t5_there]
    assert cdm(created, 3).mgrs == cdm(t5_there, 5).mgrs
    heard = [cdm(created, 3), cdm(t5_early, 5)]
    assert announced_tracks(heard, events) == {3: "T-3", 5: "T-5"}
