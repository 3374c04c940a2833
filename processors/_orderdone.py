"""When a running order is done: the airframe's word and its position together; pure, no I/O.

An autopilot's MISSION_ITEM_REACHED of the last item is necessary, not sufficient: a hostile
or confused airframe can send it (or a MISSION_CURRENT past the end, which no longer counts
at all). ``Progress`` also follows the airframe's reported positions:

- a mission ending in a waypoint (an area survey) is done once the last item was reached
  and the newest position is within ``acceptance_m`` of that waypoint;
- a mission ending in a timed loiter (observe point, a final loiter) is done once the last
  item was reached and the airframe has been on task, within the loiter radius plus
  ``acceptance_m`` of the point, without a break, for the loiter's time.

Times are the caller's monotonic seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

from gateway.domain.geodesy import distance_bearing
from gateway.domain.mission import Loiter, MissionStep

__all__ = ["Progress"]


@dataclass(slots=True)
class Progress:
    """The progress of one uploaded mission (see the module docstring)."""

    items: tuple[MissionStep, ...]
    acceptance_m: float
    reached: int = -1
    #: The newest position's distance to the last item, metres; None before one is heard.
    distance_m: float | None = None
    #: Since when (monotonic seconds) the airframe has been on task at the final loiter.
    on_task_since: float | None = None

    @property
    def last(self) -> int:
        """The last item's seq."""
        return len(self.items) - 1

    def reach(self, seq: int) -> bool:
        """Take a MISSION_ITEM_REACHED; False for an item this mission does not have."""
        if not 0 <= seq <= self.last:
            return False
        self.reached = max(self.reached, seq)
        return True

    def _radius_m(self) -> float:
        final = self.items[-1]
        return self.acceptance_m + (final.radius_m if isinstance(final, Loiter) else 0.0)

    def position(self, lat_deg: float, lon_deg: float, now_s: float) -> None:
        """Take a reported position at monotonic time ``now_s``."""
        final = self.items[-1]
        self.distance_m, _ = distance_bearing(lat_deg, lon_deg, final.lat_deg, final.lon_deg)
        if self.distance_m > self._radius_m():
            self.on_task_since = None
        elif self.on_task_since is None:
            self.on_task_since = now_s

    def on_task_left_s(self, now_s: float) -> float | None:
        """Seconds of time on task still owed at the final loiter (None: not on task now)."""
        final = self.items[-1]
        if not isinstance(final, Loiter) or self.on_task_since is None:
            return None
        return max(0.0, final.seconds - (now_s - self.on_task_since))

    def done(self, now_s: float) -> bool:
        """True once the mission is done by the airframe's word and its positions."""
        if self.reached < self.last or self.distance_m is None:
            return False
        if isinstance(self.items[-1], Loiter):
            return self.on_task_left_s(now_s) == 0.0
        return self.distance_m <= self._radius_m()

    def why_not(self, now_s: float) -> str:
        """What is still missing, in words (for a failure at the window's end)."""
        if self.reached < self.last:
            return f"the airframe reported item {self.reached} of {self.last} reached"
        if self.distance_m is None:
            return "the airframe reported no position"
        left = self.on_task_left_s(now_s)
        if isinstance(self.items[-1], Loiter) and left is not None:
            return f"{left:.0f} s of time on task were still owed"
        return (
            f"the airframe was {self.distance_m:.0f} m from the last item"
            f" (acceptance {self._radius_m():.0f} m)"
        )
