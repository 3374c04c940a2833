"""Ra 180 "new target" announcements traced to the tracks they announce, and so to targets.

A CDM carries no track id, and its position is a grid reference at the sink's precision
(10 m by default): with targets 30 m apart, giving each announcement to the target nearest
its position misattributes some (one target seems announced twice, its neighbour never). A
CDM does carry the sink's target number (``NR``, one per track for the track's life) and
was composed from one published Track event, whose grid reference (``POS``) and date-time
group (``TID``) it repeats. So each message is traced to the tracks that published an
event with the same ``POS`` and ``TID``; the candidates of every message with one number
(its ``MAL`` and its ``UPPD`` updates) are intersected, and a number whose candidates come
down to exactly one track is that track's; a track so traced is no candidate of another
number (the sink gives each track its own). A message whose event is not in the archive (a
run stopped before its last batch was written) is passed over. Each track then counts for
the target the scorer matched it to (``Score.tracks_of_target``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from gateway.events import Track
from sinks.ra180.cdm import Cdm, CdmError, CdmPrecision, dtg, mgrs_field

__all__ = ["Announcements", "announced_tracks", "announcements_by_track"]


@dataclass(frozen=True, slots=True)
class Announcements:
    """ "New target" (``MAL``) messages per target, traced through the track they announce."""

    #: Every hostile target of the truth → how many of its tracks were announced as new.
    per_target: dict[str, int]
    #: Announcements whose number could not be traced to exactly one track.
    untraced: int = 0
    #: Announcements of a track the scorer matched to no target (a false track).
    false_track: int = 0
    #: The track each announced number was traced to (None: not traced).
    tracks: dict[int, str | None] = field(default_factory=dict)


def announced_tracks(
    messages: Iterable[Cdm], events: Iterable[Track], precision_m: CdmPrecision = 10
) -> dict[int, str | None]:
    """Each target number heard → the one track its messages were composed from, or None."""
    by_key: dict[tuple[str, str], set[str]] = {}
    for event in events:
        try:
            key = (mgrs_field(event.position.lat_deg, event.position.lon_deg, precision_m),
                   dtg(event.time))  # fmt: skip
        except CdmError:
            continue  # no grid reference there: no message could have been composed from it
        by_key.setdefault(key, set()).add(event.track_id)
    candidates: dict[int, set[str] | None] = {}
    for cdm in messages:
        found = by_key.get((cdm.mgrs, cdm.dtg))
        known = candidates.get(cdm.number)
        if found is None:
            candidates.setdefault(cdm.number, None)  # its event is not in the archive (yet)
        else:
            candidates[cdm.number] = set(found) if known is None else known & found
    # One number per track and one track per number: a track traced to one number is no
    # candidate of another (repeated while that settles another number).
    settled: dict[int, str] = {}
    while True:
        newly = {
            number: next(iter(ids))
            for number, ids in candidates.items()
            if number not in settled and ids is not None and len(ids) == 1
        }
        if not newly:
            break
        settled.update(newly)
        taken = set(settled.values())
        for number, ids in candidates.items():
            if number not in settled and ids is not None:
                ids -= taken
    return {number: settled.get(number) for number in candidates}


def announcements_by_track(
    messages: Iterable[Cdm],
    events: Iterable[Track],
    tracks_of_target: Mapping[str, Iterable[str]],
    hostile_targets: Iterable[str],
    precision_m: CdmPrecision = 10,
) -> Announcements:
    """Count the ``MAL`` messages per hostile target, each through the track it announces."""
    heard = list(messages)
    traced = announced_tracks(heard, events, precision_m)
    target_of = {tid: target for target, ids in tracks_of_target.items() for tid in ids}
    per = dict.fromkeys(sorted(hostile_targets), 0)
    untraced = false_track = 0
    for cdm in heard:
        if cdm.type != "MAL":
            continue
        track_id = traced.get(cdm.number)
        target = None if track_id is None else target_of.get(track_id)
        if track_id is None:
            untraced += 1
        elif target is None or target not in per:
            false_track += 1
        else:
            per[target] += 1
    return Announcements(per, untraced, false_track, traced)
