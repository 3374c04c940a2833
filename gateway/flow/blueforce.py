"""Where the friendly units are: the latest report per unit, expiring, and the nearest to a point.

Fed by BlueForce events (the CoT source, later NFFI, units fixed in the config); read by
deconfliction: ``nearest(lat, lon)`` gives the closest current friendly unit and its geodesic
distance (WGS-84, ``gateway.domain.geodesy``). A report older than ``max_age_s`` is not a
current position and is never returned. At most ``max_units`` are kept (the unit heard from
longest ago makes room), so reports from the network cannot grow it without bound; but a
dropped unit may be a real one pushed out by a flood of reports, so for ``max_age_s`` after a
drop the picture is not ``complete`` (deconfliction then never reads "clear"); nor is it
while no unit is current at all. Units
fixed in the config are ``pin``-ned: they never expire and no report from the network can
move or evict them (a report under a pinned uid is ignored).

``nearest`` carries the unit's source, source name and provenance, and ``by_source`` counts
the current units per source and provenance, so a cue can say where its picture came from.
"""

from __future__ import annotations

import math
from collections import Counter, OrderedDict
from dataclasses import dataclass
from datetime import datetime, timedelta

from gateway.clock import Clock
from gateway.domain.geodesy import distance_bearing
from gateway.events import BlueForce, Provenance

__all__ = ["BlueForceRegistry", "NearestBlue"]


@dataclass(frozen=True, slots=True)
class NearestBlue:
    """The closest current friendly unit to a point."""

    uid: str
    callsign: str
    distance_m: float
    report_time: datetime
    source: str = ""
    source_name: str = ""
    provenance: Provenance = Provenance.UNAUTHENTICATED


class BlueForceRegistry:
    """The newest report of each friendly unit; see the module docstring."""

    def __init__(self, clock: Clock, *, max_age_s: float = 300.0, max_units: int = 10_000):
        self._clock = clock
        self.max_age = timedelta(seconds=max_age_s)
        self.max_units = max_units
        self._units: OrderedDict[str, BlueForce] = OrderedDict()
        self._pinned: dict[str, BlueForce] = {}
        self._dropped_at: datetime | None = None
        self.dropped = 0

    @property
    def complete(self) -> bool:
        """False when no unit is current, or while one dropped for room might still be.

        With no friendly position at all the gateway cannot say a target is clear of them,
        only that it does not know where they are.
        """
        if not self.current():
            return False
        return self._dropped_at is None or self._clock() - self._dropped_at > self.max_age

    def __len__(self) -> int:
        return len(self._units) + len(self._pinned)

    def pin(self, unit: BlueForce) -> None:
        """A unit fixed in the config: always current, never moved by reports."""
        self._pinned[unit.uid] = unit
        self._units.pop(unit.uid, None)

    def update(self, report: BlueForce) -> bool:
        """Keep ``report`` if it is newer than what we have for its unit; True if kept."""
        if report.uid in self._pinned:
            return False
        known = self._units.get(report.uid)
        if known is not None and report.time <= known.time:
            return False
        self._units[report.uid] = report
        self._units.move_to_end(report.uid)
        while len(self._units) > self.max_units:
            self._units.popitem(last=False)
            self._dropped_at = self._clock()
            self.dropped += 1
        return True

    def lost(self) -> None:
        """A report that never reached us (dropped on the way, e.g. a full inbox).

        It may have been a real unit's newest position, so the picture is incomplete for
        ``max_age_s``, as after a unit dropped for room.
        """
        self._dropped_at = self._clock()
        self.dropped += 1

    def current(self) -> list[BlueForce]:
        """Pinned units and every report younger than ``max_age_s`` (older ones are dropped)."""
        cutoff = self._clock() - self.max_age
        for uid in [uid for uid, r in self._units.items() if r.time < cutoff]:
            del self._units[uid]
        return [*self._pinned.values(), *self._units.values()]

    def nearest(self, lat_deg: float, lon_deg: float) -> NearestBlue | None:
        """The closest current friendly unit to the point, or None if there is none.

        A great-circle distance on the mean sphere (within 0.6 % of the ellipsoid's) ranks
        every unit cheaply; only units that could still be the nearest on the ellipsoid get
        the geodesic (geographiclib), so thousands of units cost milliseconds, not seconds.
        """
        units = self.current()
        if not units:
            return None
        rough = [
            (_sphere_m(lat_deg, lon_deg, u.position.lat_deg, u.position.lon_deg), u) for u in units
        ]
        closest = min(distance for distance, _ in rough)
        best: NearestBlue | None = None
        for distance, report in rough:
            if distance > closest * (1.0 + _SPHERE_ERROR) + 1.0:
                continue
            distance_m, _ = distance_bearing(
                lat_deg, lon_deg, report.position.lat_deg, report.position.lon_deg
            )
            if best is None or distance_m < best.distance_m:
                best = NearestBlue(
                    report.uid,
                    report.callsign,
                    distance_m,
                    report.time,
                    report.source,
                    report.source_name or report.source,
                    report.provenance,
                )
        return best

    def by_source(self) -> list[tuple[str, Provenance, int]]:
        """Current units per (source name, provenance), most units first."""
        counts = Counter((u.source_name or u.source, u.provenance) for u in self.current())
        return [(name, provenance, n) for (name, provenance), n in counts.most_common()]


#: The mean Earth radius (IUGG), and a bound on a spherical distance's relative error against
#: the WGS-84 geodesic (about 0.56 % at worst), doubled for safety.
_EARTH_M = 6_371_008.8
_SPHERE_ERROR = 0.012


def _sphere_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Haversine distance on the mean sphere, metres."""
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp, dl = p2 - p1, math.radians(lon2 - lon1)
    h = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2 * _EARTH_M * math.asin(min(1.0, math.sqrt(h)))
