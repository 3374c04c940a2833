"""Where the friendly units are: the latest report per unit, expiring, and the nearest to a point.

Fed by BlueForce events (the CoT source, later NFFI, units fixed in the config); read by
deconfliction: ``nearest(lat, lon)`` gives the closest current friendly unit and its geodesic
distance (WGS-84, ``gateway.domain.geodesy``). A report older than ``max_age_s`` is not a
current position and is never returned. At most ``max_units`` are kept (the unit heard from
longest ago makes room), so reports from the network cannot grow it without bound.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from datetime import datetime, timedelta

from gateway.clock import Clock
from gateway.domain.geodesy import distance_bearing
from gateway.events import BlueForce

__all__ = ["BlueForceRegistry", "NearestBlue"]


@dataclass(frozen=True, slots=True)
class NearestBlue:
    """The closest current friendly unit to a point."""

    uid: str
    callsign: str
    distance_m: float
    report_time: datetime


class BlueForceRegistry:
    """The newest report of each friendly unit; see the module docstring."""

    def __init__(self, clock: Clock, *, max_age_s: float = 300.0, max_units: int = 10_000):
        self._clock = clock
        self.max_age = timedelta(seconds=max_age_s)
        self.max_units = max_units
        self._units: OrderedDict[str, BlueForce] = OrderedDict()

    def __len__(self) -> int:
        return len(self._units)

    def update(self, report: BlueForce) -> bool:
        """Keep ``report`` if it is newer than what we have for its unit; True if kept."""
        known = self._units.get(report.uid)
        if known is not None and report.time <= known.time:
            return False
        self._units[report.uid] = report
        self._units.move_to_end(report.uid)
        while len(self._units) > self.max_units:
            self._units.popitem(last=False)
        return True

    def current(self) -> list[BlueForce]:
        """Every report younger than ``max_age_s``; older ones are dropped on the way."""
        cutoff = self._clock() - self.max_age
        for uid in [uid for uid, r in self._units.items() if r.time < cutoff]:
            del self._units[uid]
        return list(self._units.values())

    def nearest(self, lat_deg: float, lon_deg: float) -> NearestBlue | None:
        """The closest current friendly unit to the point, or None if there is none."""
        best: NearestBlue | None = None
        for report in self.current():
            distance_m, _ = distance_bearing(
                lat_deg, lon_deg, report.position.lat_deg, report.position.lon_deg
            )
            if best is None or distance_m < best.distance_m:
                best = NearestBlue(report.uid, report.callsign, distance_m, report.time)
        return best
