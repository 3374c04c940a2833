"""The counter-UAS cue: which fused track goes to which GUTE II battery, with what advice.

``CueDesk.consider(track)`` decides, once per track, whether to hand it off:

1. its class is one the desk cues (air threats by default) and its fused confidence has
   reached ``min_confidence`` (a weaker track is considered again on its next update);
2. the batteries able to engage it are those with an effector the table
   (``gateway.domain.effectors``) offers for its class at their range; the cue goes to the
   *nearest* of them (none able: no cue yet, counted);
3. deconfliction: the nearest current friendly unit (``BlueForceRegistry``, geodesic) is
   checked against each offered effector's danger-close radius, less the track's CEP90. The
   cue is *clear* only when every offered effector is clear; then the first is recommended.
   When it is not clear, no effector is recommended and the operator sees each one's result.
   Nor is it clear while the blue-force picture is incomplete (friendly reports dropped for
   room lately: a flood may have pushed a real unit out).

The deconfliction says where the blue-force picture came from: the nearest unit's source and
provenance, its callsign made safe and marked with what it is ("unauthenticated CoT
callsign", ``gateway.domain.peertext``), and how many current units each source gave.

Once cued, a track stays with its battery. On each later update the check is made again for
that battery; when the deconfliction or the recommendation changes, the cue goes out again as
the next *revision* of the same handoff: at once when it stops being clear (a friendly unit
now within danger close), otherwise at most every ``revision_interval_s``, so a track on the
edge cannot flood the battery. A track out of its battery's reach keeps its last cue.

A cued track that the tracker finds to be a second track of another object (``merged``, naming
the survivor) never leaves the battery holding two live cues for one object: when the survivor
has a cue of its own, the merged track's cue goes out once more as a revision with status
``superseded`` naming the survivor's cue; otherwise the cue carries on with the survivor, and
the survivor's next update goes out as its next revision with a note saying so (one cue id
per object, revisions allowed).

A cued track that the tracker gives up on (``lost``: no detection for ``lost_after_s``) does
not leave a live cue at the battery for an object nobody tracks any more: its cue goes out
once more as a final revision with status ``withdrawn``, no recommendation, no effector
offered and a note saying why ("track T-… lost: no detection since 12:03:07Z"). The desk
then forgets the track. A withdrawn cue is never revised again.

The result is a ``Handoff``: a cue with a recommendation for the battery's human operator,
who alone authorises an engagement. Nothing here can command an effector, and the event
type has no field that could carry such a command.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Literal

from gateway.domain.effectors import EffectorTable, recommend
from gateway.domain.geodesy import distance_bearing
from gateway.domain.peertext import callsign_provenance, safe_text
from gateway.events import (
    BlueSourceCount,
    Deconfliction,
    EffectorOption,
    Handoff,
    Position,
    Track,
    event_id,
)
from gateway.flow.blueforce import BlueForceRegistry, NearestBlue

__all__ = ["Battery", "CueCounts", "CueDesk"]


@dataclass(frozen=True, slots=True)
class Battery:
    """A GUTE II battery: where it stands and the effectors it has."""

    id: str
    position: Position
    effectors: frozenset[str]


@dataclass(slots=True)
class CueCounts:
    """What the desk did with the tracks it saw."""

    handed_off: int = 0
    revised: int = 0
    not_clear: int = 0
    out_of_reach: int = 0
    below_confidence: int = 0
    superseded: int = 0
    carried_on: int = 0
    withdrawn: int = 0


@dataclass(slots=True)
class _Cue:
    """The last cue sent for one track."""

    handoff_id: str
    battery: Battery
    revision: int
    clear: bool
    recommended: str | None
    sent: datetime
    note: str = ""


class CueDesk:
    """Hands each qualifying track to one battery, once; see the module docstring."""

    def __init__(
        self,
        batteries: list[Battery],
        table: EffectorTable,
        blue: BlueForceRegistry,
        *,
        classes: frozenset[str],
        min_confidence: float,
        revision_interval_s: float = 5.0,
        max_remembered: int = 100_000,
    ) -> None:
        self.batteries = batteries
        self.table = table
        self.blue = blue
        self.classes = classes
        self.min_confidence = min_confidence
        self.revision_interval_s = revision_interval_s
        self.max_remembered = max_remembered
        self.counts = CueCounts()
        self._cued: OrderedDict[str, _Cue] = OrderedDict()  # by track id

    def consider(self, track: Track) -> Handoff | None:
        """The handoff (or revision) for ``track`` if one is due now; None otherwise."""
        if track.status == "lost":
            return self._lost(track)
        if track.status == "merged":
            return self._merged(track)
        last = self._cued.get(track.track_id)
        if last is not None and last.note:
            return self._revise(track, last)  # carried on from a merged track: say so now
        if track.object_class not in self.classes:
            return None
        if last is not None:
            return self._revise(track, last)
        if track.confidence < self.min_confidence:
            self.counts.below_confidence += 1
            return None
        nearest = self._nearest(track)
        best: tuple[float, float, Battery, list[EffectorOption]] | None = None
        for battery in self.batteries:
            range_m, bearing, offered = self._offer(track, battery, nearest)
            if offered and (best is None or range_m < best[0]):
                best = (range_m, bearing, battery, offered)
        if best is None:
            self.counts.out_of_reach += 1
            return None
        range_m, bearing, battery, offered = best
        handoff_id = event_id("HO", track.track_id, battery.id)
        handoff = self._handoff(
            track, battery, handoff_id, 0, range_m, bearing, offered, nearest,
            complete=self.blue.complete,
        )  # fmt: skip
        self._remember(track.track_id, _Cue(
            handoff_id, battery, 0, handoff.deconfliction.clear,
            handoff.recommended_effector, track.time,
        ))  # fmt: skip
        self.counts.handed_off += 1
        return handoff

    def _merged(self, track: Track) -> Handoff | None:
        """``track`` was folded into ``track.merged_into``: supersede or carry on its cue."""
        cue = self._cued.pop(track.track_id, None)
        survivor_id = track.merged_into
        if cue is None or survivor_id is None:
            return None
        survivor = self._cued.get(survivor_id)
        if survivor is None:
            cue.note = (
                f"track {track.track_id} merged into {survivor_id}; this cue now follows"
                f" {survivor_id}"
            )
            self._remember(survivor_id, cue)
            self.counts.carried_on += 1
            return None
        nearest = self._nearest(track)
        range_m, bearing, offered = self._offer(track, cue.battery, nearest)
        self.counts.superseded += 1
        return self._handoff(
            track, cue.battery, cue.handoff_id, cue.revision + 1, range_m, bearing, offered,
            nearest, complete=self.blue.complete, status="superseded",
            superseded_by=survivor.handoff_id,
            note=(
                f"track {track.track_id} merged into {survivor_id}, which cue"
                f" {survivor.handoff_id} follows: drop this cue"
            ),
        )  # fmt: skip

    def _lost(self, track: Track) -> Handoff | None:
        """``track`` is lost: withdraw its cue, once, and forget it."""
        cue = self._cued.pop(track.track_id, None)
        if cue is None:
            return None
        nearest = self._nearest(track)
        range_m, bearing, _ = self._offer(track, cue.battery, nearest)
        self.counts.withdrawn += 1
        return self._handoff(
            track, cue.battery, cue.handoff_id, cue.revision + 1, range_m, bearing, [],
            nearest, complete=self.blue.complete, status="withdrawn",
            note=(
                f"track {track.track_id} lost: no detection since"
                f" {track.last_seen.astimezone(UTC):%Y-%m-%dT%H:%M:%SZ}; the gateway no"
                " longer tracks this object: drop this cue"
            ),
        )  # fmt: skip

    def _revise(self, track: Track, last: _Cue) -> Handoff | None:
        nearest = self._nearest(track)
        range_m, bearing, offered = self._offer(track, last.battery, nearest)
        if not offered and not last.note:
            return None  # out of its battery's reach for now: the last cue stands
        complete = self.blue.complete
        clear = complete and bool(offered) and all(o.deconfliction_clear for o in offered)
        recommended = offered[0].effector if clear else None
        if not last.note:
            if (clear, recommended) == (last.clear, last.recommended):
                return None
            waited = (track.time - last.sent).total_seconds()
            if clear and waited < self.revision_interval_s:
                return None  # good news can wait; losing "clear" never does
        revision = last.revision + 1
        handoff = self._handoff(
            track, last.battery, last.handoff_id, revision, range_m, bearing, offered, nearest,
            complete=complete, note=last.note,
        )  # fmt: skip
        last.revision, last.clear, last.recommended, last.sent, last.note = (
            revision, clear, recommended, track.time, "",
        )  # fmt: skip
        self._cued.move_to_end(track.track_id)
        self.counts.revised += 1
        return handoff

    def _nearest(self, track: Track) -> NearestBlue | None:
        return self.blue.nearest(track.position.lat_deg, track.position.lon_deg)

    def _offer(
        self, track: Track, battery: Battery, nearest: NearestBlue | None
    ) -> tuple[float, float, list[EffectorOption]]:
        """Range and bearing from ``battery``, and the effectors it has that the table offers."""
        range_m, bearing = distance_bearing(
            battery.position.lat_deg,
            battery.position.lon_deg,
            track.position.lat_deg,
            track.position.lon_deg,
        )
        offered = [
            EffectorOption(
                effector=r.effector,
                deconfliction_clear=r.deconfliction_clear,
                danger_close_m=r.danger_close_m,
            )
            for r in recommend(
                self.table,
                track.object_class,
                range_m,
                None if nearest is None else nearest.distance_m,
                uncertainty_m=track.cep90_m,
            )
            if r.effector in battery.effectors
        ]
        return range_m, bearing % 360.0 if bearing % 360.0 < 360.0 else 0.0, offered

    def _handoff(
        self,
        track: Track,
        battery: Battery,
        handoff_id: str,
        revision: int,
        range_m: float,
        bearing: float,
        offered: list[EffectorOption],
        nearest: NearestBlue | None,
        *,
        complete: bool,
        status: Literal["active", "superseded", "withdrawn"] = "active",
        superseded_by: str | None = None,
        note: str = "",
    ) -> Handoff:
        clear = complete and bool(offered) and all(o.deconfliction_clear for o in offered)
        if not clear and status != "withdrawn":
            self.counts.not_clear += 1
        return Handoff(
            event_id=handoff_id if revision == 0 else f"{handoff_id}-r{revision}",
            handoff_id=handoff_id,
            revision=revision,
            status=status,
            superseded_by=superseded_by,
            note=note,
            time=track.time,
            battery=battery.id,
            battery_position=battery.position,
            track=track,
            range_m=range_m,
            bearing_deg=bearing,
            recommended_effector=offered[0].effector if clear and status == "active" else None,
            options=tuple(offered),
            deconfliction=self._deconfliction(clear, nearest, complete=complete),
        )

    def _deconfliction(
        self, clear: bool, nearest: NearestBlue | None, *, complete: bool
    ) -> Deconfliction:
        """The blue-force check, its peer text made safe and marked by provenance."""
        sources = tuple(
            BlueSourceCount(source=safe_text(name, 64), provenance=provenance, units=units)
            for name, provenance, units in self.blue.by_source()
        )
        if nearest is None:
            return Deconfliction(
                clear=clear,
                blue_units_considered=len(self.blue),
                blue_picture_complete=complete,
                blue_sources=sources,
            )
        callsign = safe_text(nearest.callsign) or None
        return Deconfliction(
            clear=clear,
            nearest_blue_uid=safe_text(nearest.uid, 64),
            nearest_blue_callsign=callsign,
            nearest_blue_m=nearest.distance_m,
            blue_units_considered=len(self.blue),
            blue_picture_complete=complete,
            nearest_blue_callsign_provenance=(
                None
                if callsign is None
                else callsign_provenance(nearest.provenance, nearest.source)
            ),
            nearest_blue_source=safe_text(nearest.source_name, 64),
            nearest_blue_provenance=nearest.provenance,
            blue_sources=sources,
        )

    def _remember(self, track_id: str, cue: _Cue) -> None:
        self._cued[track_id] = cue
        while len(self._cued) > self.max_remembered:
            self._cued.popitem(last=False)
