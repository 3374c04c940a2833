"""Which live tracks a detection could gate with: a spatial grid for fresh tracks, the rest whole.

A track is *fresh* while it was updated within the horizon (``coast_after_s``); each is filed
in a ``GridIndex`` at its position with its *reach*, how far from there a detection its gate
passes could lie within the horizon (the tracker computes it). ``candidates`` queries the grid
with the largest reach of any fresh track plus the detection's own gate width, so it misses no
fresh track the gate could pass. A track silent beyond the horizon (``expire``) is kept in a
small set checked whole: a coasting track's gate keeps widening. With ``exhaustive`` every
track is a candidate (for tests and the benchmark to compare).

The largest reach is kept without a scan: each fresh track's reach is counted in a bucket of
a geometric ladder (10 % steps), and the query uses the top of the highest bucket in use, so
one wide track raises it only while it is fresh. Expiry is a heap holding one (deadline, id)
entry per fresh track, pushed again with the new deadline when found early. Every operation
costs O(log n) or less in live tracks. Up to ``_FEW`` live tracks, every one is a candidate.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Mapping

from gateway.flow.gridindex import GridIndex
from gateway.flow.localplane import GridPlane
from tracking.track import TrackState

__all__ = ["TrackIndex"]

#: Radii up to this (m) use a cached stretch of the plane; larger ones are computed.
_CACHED_RADIUS_M = 50_000.0
#: Up to this many live tracks every one is a candidate (cheaper than a grid query).
_FEW = 16
#: The reach ladder's step: each bucket's top is 10 % above the one below.
_STEP = 1.1
_LOG_STEP = math.log(_STEP)


class TrackIndex:
    """Gating candidates over the tracker's ``tracks`` (shared, not copied)."""

    def __init__(
        self, tracks: Mapping[str, TrackState], cell_m: float, horizon_s: float, *, exhaustive: bool
    ) -> None:
        self.horizon_s = horizon_s
        self._tracks = tracks
        self._exhaustive = exhaustive
        self._grid: GridIndex[str] = GridIndex(cell_m)
        self._plane: GridPlane | None = None
        self._stretch: dict[int, float] = {}
        self._wide: set[str] = set()
        self._expiry: list[tuple[float, str]] = []  # (deadline, track id) per queued track
        self._queued: set[str] = set()
        self._bucket_of: dict[str, int] = {}  # fresh track → its reach's bucket
        self._buckets: dict[int, int] = {}  # bucket → fresh tracks in it
        self._top = -1  # the highest bucket in use, -1 when none

    @property
    def reach_m(self) -> float:
        """At least the largest reach of any fresh track (m)."""
        return 0.0 if self._top < 0 else _STEP ** (self._top + 1)

    def _count(self, track_id: str, reach_m: float | None) -> None:
        """Move the track's reach to the bucket of ``reach_m`` (None: out of the ladder)."""
        bucket = None
        if reach_m is not None:
            bucket = max(0, math.ceil(math.log(max(reach_m, 1.0)) / _LOG_STEP))
            if self._bucket_of.get(track_id) == bucket:
                return  # the usual case: the reach changed by less than a step
        old = self._bucket_of.pop(track_id, None)
        if old is not None:
            left = self._buckets[old] - 1
            if left:
                self._buckets[old] = left
            else:
                del self._buckets[old]
        if bucket is not None:
            self._bucket_of[track_id] = bucket
            self._buckets[bucket] = self._buckets.get(bucket, 0) + 1
            self._top = max(self._top, bucket)
        while self._top >= 0 and self._top not in self._buckets:
            self._top -= 1

    def is_wide(self, track_id: str) -> bool:
        """Whether the track is silent beyond the horizon (checked whole)."""
        return track_id in self._wide

    def file(self, state: TrackState) -> None:
        """(Re)file ``state`` at its position, fresh from its update, with ``state.reach_m``."""
        if self._plane is None:
            self._plane = GridPlane(state.lat_deg, state.lon_deg)
        self._count(state.track_id, state.reach_m)
        x, y = self._plane.forward(state.lat_deg, state.lon_deg)
        if state.track_id in self._grid:
            self._grid.move(state.track_id, x, y)
        else:
            self._grid.insert(state.track_id, x, y)
        self._wide.discard(state.track_id)
        if state.track_id not in self._queued:
            # One entry per track: an entry found early at its deadline (the track was updated
            # since) is pushed again with the new one, so an update costs no heap operation.
            self._queued.add(state.track_id)
            heapq.heappush(self._expiry, (state.updated_s + self.horizon_s, state.track_id))

    def remove(self, track_id: str) -> None:
        """Forget the track (if filed)."""
        if track_id in self._grid:
            self._grid.remove(track_id)
        self._queued.discard(track_id)  # its heap entry is skipped when it comes up
        self._wide.discard(track_id)
        self._count(track_id, None)

    @property
    def wide(self) -> list[str]:
        """The tracks silent beyond the horizon, sorted."""
        return sorted(self._wide)

    def expire(self, at_s: float) -> list[str]:
        """The tracks that went silent beyond the horizon by ``at_s``, now checked whole."""
        out: list[str] = []
        while self._expiry and self._expiry[0][0] <= at_s:
            _, track_id = heapq.heappop(self._expiry)
            state = self._tracks.get(track_id)
            if state is None or track_id not in self._queued:
                continue  # removed (and perhaps filed again: then it has a newer entry)
            deadline = state.updated_s + self.horizon_s
            if deadline > at_s:
                heapq.heappush(self._expiry, (deadline, track_id))
                continue
            self._queued.discard(track_id)
            self._wide.add(track_id)
            self._count(track_id, None)
            out.append(track_id)
        return out

    def candidates(self, lat: float, lon: float, widen_m: float) -> list[str]:
        """Every track whose gate could pass a detection at (lat, lon) ``widen_m`` wide."""
        if self._exhaustive or self._plane is None or len(self._tracks) <= _FEW:
            return list(self._tracks)  # a handful: checking each beats querying the grid
        x, y = self._plane.forward(lat, lon)
        near = self._grid.within(x, y, self._plane_radius(lat, self.reach_m + widen_m + 1.0))
        if not self._wide:
            return near
        seen = set(near)
        return near + [t for t in self._wide if t not in seen]

    def _plane_radius(self, lat: float, radius_m: float) -> float:
        """``GridPlane.grid_radius_m``, its stretch cached per 0.01° of latitude (taken over
        the largest cached radius, so it bounds every smaller one there)."""
        plane = self._plane
        if plane is None or radius_m > _CACHED_RADIUS_M:
            return radius_m if plane is None else plane.grid_radius_m(lat, radius_m)
        band = math.floor(lat * 100.0)
        stretch = self._stretch.get(band)
        if stretch is None:
            edges = (band / 100.0, (band + 1) / 100.0)
            stretch = max(plane.grid_radius_m(e, _CACHED_RADIUS_M) for e in edges)
            stretch /= _CACHED_RADIUS_M
            self._stretch[band] = stretch
        return radius_m * stretch + 1.0
