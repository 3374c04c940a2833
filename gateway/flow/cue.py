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

The result is a ``Handoff``: a cue with a recommendation for the battery's human operator,
who alone authorises an engagement. Nothing here can command an effector, and the event
type has no field that could carry such a command.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

from gateway.domain.effectors import EffectorTable, recommend
from gateway.domain.geodesy import distance_bearing
from gateway.events import (
    Deconfliction,
    EffectorOption,
    Handoff,
    Position,
    Track,
    event_id,
)
from gateway.flow.blueforce import BlueForceRegistry

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
    not_clear: int = 0
    out_of_reach: int = 0
    below_confidence: int = 0


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
        max_remembered: int = 100_000,
    ) -> None:
        self.batteries = batteries
        self.table = table
        self.blue = blue
        self.classes = classes
        self.min_confidence = min_confidence
        self.max_remembered = max_remembered
        self.counts = CueCounts()
        self._cued: OrderedDict[str, str] = OrderedDict()  # track id -> handoff id

    def forget(self, track_id: str) -> None:
        """The track is lost: it no longer holds a place among the cued."""
        self._cued.pop(track_id, None)

    def consider(self, track: Track) -> Handoff | None:
        """The handoff for ``track`` if it is due now; None otherwise (see module docstring)."""
        if track.status == "lost":
            self.forget(track.track_id)
            return None
        if track.track_id in self._cued or track.object_class not in self.classes:
            return None
        if track.confidence < self.min_confidence:
            self.counts.below_confidence += 1
            return None
        where = track.position
        nearest = self.blue.nearest(where.lat_deg, where.lon_deg)
        nearest_m = None if nearest is None else nearest.distance_m
        best: tuple[float, float, Battery, list[EffectorOption]] | None = None
        for battery in self.batteries:
            range_m, bearing = distance_bearing(
                battery.position.lat_deg, battery.position.lon_deg, where.lat_deg, where.lon_deg
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
                    nearest_m,
                    uncertainty_m=track.cep90_m,
                )
                if r.effector in battery.effectors
            ]
            if offered and (best is None or range_m < best[0]):
                best = (range_m, bearing, battery, offered)
        if best is None:
            self.counts.out_of_reach += 1
            return None
        range_m, bearing, battery, offered = best
        clear = all(option.deconfliction_clear for option in offered)
        handoff_id = event_id("HO", track.track_id, battery.id)
        self._remember(track.track_id, handoff_id)
        self.counts.handed_off += 1
        if not clear:
            self.counts.not_clear += 1
        return Handoff(
            event_id=handoff_id,
            handoff_id=handoff_id,
            time=track.time,
            battery=battery.id,
            battery_position=battery.position,
            track=track,
            range_m=range_m,
            bearing_deg=bearing % 360.0 if bearing % 360.0 < 360.0 else 0.0,
            recommended_effector=offered[0].effector if clear else None,
            options=tuple(offered),
            deconfliction=Deconfliction(
                clear=clear,
                nearest_blue_uid=None if nearest is None else nearest.uid,
                nearest_blue_callsign=None if nearest is None else nearest.callsign or None,
                nearest_blue_m=nearest_m,
                blue_units_considered=len(self.blue),
            ),
        )

    def _remember(self, track_id: str, handoff_id: str) -> None:
        self._cued[track_id] = handoff_id
        while len(self._cued) > self.max_remembered:
            self._cued.popitem(last=False)
