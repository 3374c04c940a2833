"""Detections to tracks: association, lifecycle and emission, with no I/O.

``Tracker.update(detection)`` associates a detection with the best live track or starts one,
and ``Tracker.tick(now)`` ages tracks and flushes coalesced updates; both return the Track
events to publish. Time comes only from the detections and from ``tick``, so a test drives
it with any clock. The estimate of one track lives in ``gateway.flow.trackstate``.

**Association.** A detection is gated against each live track last updated within
``max_gap_s``: the distance from the track's constant-velocity prediction, in the local
tangent plane, must be at most ``gate_sigma`` combined σ (√(σ_det² + σ_track²)). The gated
track with the smallest distance in σ wins (ties by track id). Candidates come from a
``GridIndex`` (``index="grid"``) queried with a radius certain to contain every gated track;
``index="all_pairs"`` scans every track and exists so a benchmark can compare the two. Both
apply the same exact gate, so they give the same tracks.

**Class evidence** is the Dempster combination of each source's newest report (see
``trackstate``). A detection in total conflict with a gated track (its evidence and the
track's exclude each other) is not associated with that track: the next candidate is tried,
else it starts a new track; such detections are counted in ``counts.total_conflict``.

**Lifecycle.** Track ids (``T-<BOOT_ID>-0001``) are stable for a track's life and unique
across restarts. The first detection emits "created"; later ones emit "updated" at most once
per ``update_interval_s`` per track (a change of class is emitted at once), and ``tick``
flushes an update held back. A track without a detection for ``lost_after_s`` is emitted
once as "lost" and forgotten. At most ``max_tracks`` live at once: a detection that would
start another is refused and counted, so memory stays bounded.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from functools import cache
from typing import Literal

from gateway.domain.evidence import MassFunction, TotalConflict, simple_support
from gateway.domain.sidc import Hostility, symbol_codes
from gateway.domain.targeting import cep50_m, cep90_m
from gateway.events import BOOT_ID, Detection, Position, Track, Velocity, event_id
from gateway.flow.gridindex import GridIndex
from gateway.flow.localplane import GridPlane, displace, offset_m
from gateway.flow.trackstate import MIN_SIGMA_M, Source, TrackState, fuse_sources

__all__ = ["DEFAULT_CLASSES", "OTHER", "Tracker", "TrackerCounts", "TrackerSettings"]

#: The object classes of the FISCHER dialect (``gateway.fleet.dialect.CLASS_NAMES``).
DEFAULT_CLASSES: tuple[str, ...] = (
    "tank",
    "armour",
    "infantry_platoon",
    "uav",
    "loitering_munition",
)
#: The frame's catch-all: every class not configured maps to it.
OTHER = "other"

Index = Literal["grid", "all_pairs"]


@dataclass(frozen=True, slots=True)
class TrackerSettings:
    """A tracker's parameters; ``processors.fusion.FusionConfig`` validates them for operators."""

    classes: tuple[str, ...] = DEFAULT_CLASSES
    hostile_classes: frozenset[str] = frozenset({"tank", "armour", "loitering_munition"})
    gate_sigma: float = 3.0
    max_gap_s: float = 10.0
    lost_after_s: float = 30.0
    max_tracks: int = 5000
    update_interval_s: float = 1.0
    process_noise_mps: float = 5.0
    max_speed_mps: float = 100.0
    velocity_window: int = 6
    index: Index = "grid"
    cell_m: float = 2000.0
    loitering_munition: Literal["uav_attack", "missile"] = "uav_attack"


@dataclass(slots=True)
class TrackerCounts:
    """What the tracker did, as plain counters."""

    associated: int = 0
    created: int = 0
    refused_full: int = 0
    total_conflict: int = 0
    lost: int = 0
    merged: int = 0


@cache
def _sidc(object_class: str, hostility: Hostility, loitering_munition: str) -> str | None:
    variant: Literal["uav_attack", "missile"] = (
        "missile" if loitering_munition == "missile" else "uav_attack"
    )
    try:
        return symbol_codes(object_class, hostility, loitering_munition=variant).sidc_2525c
    except KeyError:
        return None  # "other" and classes the symbol table lacks: the sink picks a generic one


#: Detections a track needs before it may be merged with a twin.
_ESTABLISHED = 3


@dataclass(slots=True)
class _Gated:
    score: float
    track_id: str


class Tracker:
    """Fuses detections into tracks; see the module docstring for the rules."""

    def __init__(self, settings: TrackerSettings | None = None) -> None:
        self.settings = s = settings or TrackerSettings()
        self.frame = frozenset(s.classes) | {OTHER}
        self.counts = TrackerCounts()
        self._tracks: dict[str, TrackState] = {}
        self._pending: set[str] = set()
        self._next = 0
        self._grid: GridIndex[str] = GridIndex(s.cell_m)
        self._plane: GridPlane | None = None
        self._sigma_max_m = MIN_SIGMA_M
        self._sigma_v_max = math.hypot(0.5 * s.max_speed_mps, s.process_noise_mps)

    def __len__(self) -> int:
        return len(self._tracks)

    @property
    def track_ids(self) -> list[str]:
        """The live tracks' ids, oldest first."""
        return list(self._tracks)

    def update(self, detection: Detection) -> list[Track]:
        """Fold ``detection`` into the tracks; the Track events it causes (zero or one)."""
        s = self.settings
        at_s = detection.time.timestamp()
        sigma_m = max(detection.sigma_h_m, MIN_SIGMA_M)
        self._sigma_max_m = max(self._sigma_max_m, sigma_m)
        name = detection.object_class if detection.object_class in self.frame else OTHER
        mass = simple_support(self.frame, {name}, detection.confidence)
        source: Source = (detection.airframe, detection.sensor)
        lat, lon = detection.position.lat_deg, detection.position.lon_deg
        conflicted = False
        for gated in self._gate(lat, lon, at_s, sigma_m):
            state = self._tracks[gated.track_id]
            sources = {**state.sources, source: mass}
            try:
                masses, k = fuse_sources(sources)
            except TotalConflict:
                conflicted = True
                continue
            if conflicted:
                self.counts.total_conflict += 1
            self.counts.associated += 1
            state.set_classes(sources, masses, k)
            self._absorb(state, detection, at_s, sigma_m)
            survivor, lost = self._merge_twin(state, at_s, detection.time)
            return lost + self._updated(survivor, at_s)
        if conflicted:
            self.counts.total_conflict += 1
        if len(self._tracks) >= s.max_tracks:
            self.counts.refused_full += 1
            return []
        return [self._start(detection, at_s, sigma_m, source, mass)]

    def tick(self, now: datetime) -> list[Track]:
        """Age tracks and flush held-back updates at ``now``; the Track events to publish."""
        s = self.settings
        now_s = now.timestamp()
        out: list[Track] = []
        for track_id in [
            t for t, st in self._tracks.items() if now_s - st.updated_s >= s.lost_after_s
        ]:
            state = self._tracks.pop(track_id)
            self._pending.discard(track_id)
            if track_id in self._grid:
                self._grid.remove(track_id)
            self.counts.lost += 1
            out.append(self._event(state, "lost", now))
        for track_id in sorted(self._pending):
            state = self._tracks[track_id]
            if now_s - state.emitted_s >= s.update_interval_s:
                self._pending.discard(track_id)
                out.append(self._emit(state, "updated", now_s))
        return out

    def _merge_twin(
        self, state: TrackState, at_s: float, time: datetime
    ) -> tuple[TrackState, list[Track]]:
        """Merge the live track that ``state`` has just come within the gate of, if any.

        Two tracks of one target happen when a detection misses the gate (a 3σ gate passes
        98.9 % of true matches) and starts a second track that then follows the same target.
        Once the two estimates lie within ``gate_sigma`` of each other (combined σ) and their
        class evidence does not exclude each other, the younger is folded into the older: the
        older id lives on, the younger is published once as lost. Returns the survivor and the
        lost event (none if no twin).
        """
        s = self.settings
        for other_id in self._candidates(state.lat_deg, state.lon_deg, state.sigma_m):
            other = self._tracks[other_id]
            if other is state or abs(at_s - other.updated_s) > s.max_gap_s:
                continue
            if min(state.detection_count, other.detection_count) < _ESTABLISHED:
                continue  # one or two reports are no evidence that two tracks are one target
            dt = abs(at_s - other.updated_s)
            if other.east_mps is None and dt > 1.0:
                continue  # no velocity yet: where it is now is anybody's guess
            # Its estimate carried to now, with its own σ and process noise only: the
            # velocity prior's width says where a target *could* be, not that two are one.
            o_lat, o_lon, _ = other.predict(at_s, s.process_noise_mps, s.max_speed_mps)
            o_sigma = math.hypot(other.sigma_m, s.process_noise_mps * dt)
            east, north = offset_m(o_lat, o_lon, state.lat_deg, state.lon_deg)
            if math.hypot(east, north) > s.gate_sigma * math.hypot(state.sigma_m, o_sigma):
                continue
            sources = {**other.sources, **state.sources}  # state holds the newest report
            try:
                masses, k = fuse_sources(sources)
            except TotalConflict:
                continue
            order = list(self._tracks)
            old, young = (
                (state, other) if order.index(state.track_id) < order.index(other_id)
                else (other, state)
            )  # fmt: skip
            old.set_classes(sources, masses, k)
            # The two estimates, inverse-variance weighted, at the newest time.
            p_var, q_var = o_sigma**2, state.sigma_m**2
            gain = p_var / (p_var + q_var)
            lat, lon = displace(o_lat, o_lon, gain * east, gain * north)
            old.lat_deg, old.lon_deg = lat, lon
            old.sigma_m = math.sqrt(p_var * q_var / (p_var + q_var))
            old.updated_s = max(old.updated_s, young.updated_s)
            if young.east_mps is not None and (
                old.east_mps is None or young.velocity_sigma_mps < old.velocity_sigma_mps
            ):
                old.east_mps, old.north_mps = young.east_mps, young.north_mps
                old.velocity_sigma_mps = young.velocity_sigma_mps
            old.history.append((old.updated_s, lat, lon, old.sigma_m))
            for name, subtype in young.subtypes.items():
                old.subtypes.setdefault(name, subtype)
            old.detection_ids.extend(young.detection_ids)
            old.detection_count += young.detection_count
            old.airframes |= young.airframes
            old.sensors |= young.sensors
            old.first_seen = min(old.first_seen, young.first_seen)
            old.last_seen = max(old.last_seen, young.last_seen)
            if young.alt_msl_m is not None and young.last_seen >= old.last_seen:
                old.alt_msl_m = young.alt_msl_m
            del self._tracks[young.track_id]
            self._pending.discard(young.track_id)
            if young.track_id in self._grid:
                self._grid.remove(young.track_id)
            if self._plane is not None:
                self._grid.move(old.track_id, *self._plane.forward(lat, lon))
            self.counts.merged += 1
            old.emitted_class = ""  # its picture changed: the next update goes out at once
            return old, [self._event(young, "lost", time)]
        return state, []

    def _gate(self, lat: float, lon: float, at_s: float, sigma_m: float) -> list[_Gated]:
        s = self.settings
        gated: list[_Gated] = []
        for track_id in self._candidates(lat, lon, sigma_m):
            state = self._tracks[track_id]
            if abs(at_s - state.updated_s) > s.max_gap_s:
                continue
            p_lat, p_lon, p_sigma = state.predict(at_s, s.process_noise_mps, s.max_speed_mps)
            east, north = offset_m(p_lat, p_lon, lat, lon)
            score = math.hypot(east, north) / math.sqrt(sigma_m**2 + p_sigma**2)
            if score <= s.gate_sigma:
                gated.append(_Gated(score, track_id))
        gated.sort(key=lambda g: (g.score, g.track_id))
        return gated

    def _candidates(self, lat: float, lon: float, sigma_m: float) -> Iterable[str]:
        s = self.settings
        if s.index == "all_pairs" or self._plane is None:
            return list(self._tracks)
        # Every gated track is within the gate of its prediction, and its prediction within
        # max_speed·max_gap of where it is filed; σ_track is at most the largest σ seen grown
        # by the largest σᵥ over max_gap.
        sigma_track = math.hypot(self._sigma_max_m, self._sigma_v_max * s.max_gap_s)
        reach_m = s.gate_sigma * math.hypot(sigma_m, sigma_track) + s.max_speed_mps * s.max_gap_s
        x, y = self._plane.forward(lat, lon)
        return self._grid.within(x, y, self._plane.grid_radius_m(lat, reach_m))

    def _absorb(self, state: TrackState, detection: Detection, at_s: float, sigma_m: float) -> None:
        s = self.settings
        state.fuse_position(
            at_s,
            detection.position.lat_deg,
            detection.position.lon_deg,
            sigma_m,
            process_noise_mps=s.process_noise_mps,
            max_speed_mps=s.max_speed_mps,
            velocity_window=s.velocity_window,
        )
        if detection.position.alt_msl_m is not None and detection.time >= state.last_seen:
            state.alt_msl_m = detection.position.alt_msl_m
        if detection.subtype:
            name = detection.object_class if detection.object_class in self.frame else OTHER
            state.subtypes[name] = detection.subtype
        state.detection_ids.append(detection.event_id)
        state.detection_count += 1
        state.airframes.add(detection.airframe)
        state.sensors.add(detection.sensor)
        state.first_seen = min(state.first_seen, detection.time)
        state.last_seen = max(state.last_seen, detection.time)
        if self._plane is not None:
            x, y = self._plane.forward(state.lat_deg, state.lon_deg)
            self._grid.move(state.track_id, x, y)

    def _start(
        self,
        detection: Detection,
        at_s: float,
        sigma_m: float,
        source: Source,
        mass: MassFunction,
    ) -> Track:
        self._next += 1
        self.counts.created += 1
        track_id = f"T-{BOOT_ID}-{self._next:04d}"
        lat, lon = detection.position.lat_deg, detection.position.lon_deg
        best, belief = mass.best()
        state = TrackState(
            track_id=track_id,
            lat_deg=lat,
            lon_deg=lon,
            sigma_m=sigma_m,
            updated_s=at_s,
            first_seen=detection.time,
            last_seen=detection.time,
            sources={source: mass},
            classes=mass,
            class_conflict=0.0,
            object_class=best,
            confidence=belief,
        )
        state.history.append((at_s, lat, lon, sigma_m))
        state.alt_msl_m = detection.position.alt_msl_m
        if detection.subtype:
            state.subtypes[best] = detection.subtype
        state.detection_ids.append(detection.event_id)
        state.detection_count = 1
        state.airframes.add(detection.airframe)
        state.sensors.add(detection.sensor)
        self._tracks[track_id] = state
        if self._plane is None:
            self._plane = GridPlane(lat, lon)
        self._grid.insert(track_id, *self._plane.forward(lat, lon))
        return self._emit(state, "created", at_s)

    def _updated(self, state: TrackState, at_s: float) -> list[Track]:
        is_due = at_s - state.emitted_s >= self.settings.update_interval_s
        if state.object_class != state.emitted_class or is_due:
            self._pending.discard(state.track_id)
            return [self._emit(state, "updated", at_s)]
        self._pending.add(state.track_id)
        return []

    def _emit(self, state: TrackState, status: Literal["created", "updated"], at_s: float) -> Track:
        state.emitted_s = max(state.emitted_s, at_s)
        state.emitted_class = state.object_class
        return self._event(state, status, state.last_seen)

    def _event(
        self, state: TrackState, status: Literal["created", "updated", "lost"], time: datetime
    ) -> Track:
        s = self.settings
        state.sequence += 1
        hostility: Hostility = "hostile" if state.object_class in s.hostile_classes else "suspect"
        velocity = None
        if state.east_mps is not None and state.north_mps is not None:
            velocity = Velocity(north_mps=state.north_mps, east_mps=state.east_mps, down_mps=0.0)
        return Track(
            event_id=event_id(state.track_id, state.sequence),
            track_id=state.track_id,
            time=time,
            status=status,
            object_class=state.object_class,
            subtype=state.subtypes.get(state.object_class, ""),
            confidence=state.confidence,
            class_conflict=state.class_conflict,
            position=Position(
                lat_deg=state.lat_deg, lon_deg=state.lon_deg, alt_msl_m=state.alt_msl_m
            ),
            cep50_m=cep50_m([state.sigma_m]),
            cep90_m=cep90_m([state.sigma_m]),
            velocity=velocity,
            speed_mps=state.speed_mps,
            course_deg=state.course_deg,
            detection_ids=tuple(state.detection_ids),
            detection_count=state.detection_count,
            airframes=tuple(sorted(state.airframes)),
            sensors=tuple(sorted(state.sensors)),
            first_seen=state.first_seen,
            last_seen=state.last_seen,
            hostility=hostility,
            sidc=_sidc(state.object_class, hostility, s.loitering_munition),
        )
