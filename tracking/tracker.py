"""Detections to tracks: frames, joint association, track life and emission, with no I/O.

``Tracker.update(detection)`` collects a detection into its sensor frame (same airframe,
sensor and time); a frame is processed as soon as it holds the ``frame_size`` its detections
declare (the largest, when they differ), when its source's next frame starts, on ``flush()``
or on ``tick(now)``, which also ages tracks and sends held-back updates. A detection of a frame
already processed (a late frame-mate, or one past a ``frame_size`` declared too small) starts a
frame of its own. Each returns the
Track events to publish. Time comes only from the detections and from ``tick``.

**A frame** is processed at once: every detection is gated against every live track within
reach (Mahalanobis d² of the position against the track's constant-velocity prediction at most
``gate_sigma``²; class evidence not in total conflict), and the frame's detections are matched
to those tracks jointly by global nearest neighbour (``tracking.assign``). The detections are
put in a canonical order first, so the order they arrived in never changes the tracks. A
detection left unmatched starts a tentative track.

**Candidates** come from a ``GridIndex`` of the tracks' filed positions, queried with a
radius certain to hold every *fresh* track the gate could pass (its reach: how far its
prediction could move and how wide its gate could be within ``coast_after_s`` of its last
update); tracks silent longer (coasting, few) are scanned whole. ``index="all_pairs"`` scans
every track and exists so tests and the benchmark can compare. Both give the same tracks.

**Life.** Tentative until ``confirm_hits`` detections within its first ``confirm_window``
chances (``tracking.track``); only then published ("created"). A chance missed is a frame
from a source that has seen the track with a detection inside its gate that went elsewhere.
Confirmed tracks publish "updated" at most every ``update_interval_s`` (a class change at
once); without a detection for ``coast_after_s`` a track coasts (kept, predicted, not
published) and is published "lost" after ``lost_after_s``. A tentative track that can no
longer be confirmed, or has had no detection for ``coast_after_s``, is dropped unpublished.

**Merge.** Two tracks whose estimates agree in position and velocity (within ``merge_sigma``
on both) for ``merge_after`` updates in a row, with class evidence that does not exclude each
other, are one object: the younger is folded into the older and published once as "merged"
naming the survivor (never "lost"); a tentative twin is folded in silently.

**Speed prior.** A new track's velocity σ per axis is its class's speed limit
(``tracking.priors``, times ``speed_scale``); an estimate faster than the limit is pulled back
along its course as a measurement of the speed at the limit (σ ``speed_prior_sigma`` × limit)
would, with the covariance left as it was (``Estimate.update_speed``). It penalises, never
clamps.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from datetime import datetime
from functools import lru_cache

from gateway.domain.evidence import MassFunction, TotalConflict, simple_support
from gateway.events import BOOT_ID, Detection, Track
from gateway.flow.localplane import offset_m
from tracking.assign import assign
from tracking.emit import Status, track_event
from tracking.index import TrackIndex
from tracking.kalman import POSITION, Estimate, Innovation
from tracking.merge import agree, elder, fold
from tracking.settings import OTHER, TrackerCounts, TrackerSettings
from tracking.track import MIN_SIGMA_M, Source, TrackState, fuse_sources

__all__ = ["Tracker"]

#: A frame holding more detections than this is processed at once (memory stays bounded).
MAX_FRAME = 1000
#: Detection-track pairs one frame may examine (each a few µs of Python on the event loop):
#: a real frame needs far fewer (50 detections near 50 tracks: 2,500), while a crafted one
#: (1,000 detections 2 m apart among 1,000 tracks) would cost a million and stall the node
#: for seconds. The detections of a frame past the budget are refused and counted
#: (``overload_refused``), in the frame's canonical order, so the outcome does not depend on
#: the order they came in.
MAX_FRAME_PAIRS = 20_000
#: Adaptive process noise (a continuous noise-level adjustment): after ``_NIS_AFTER`` hits a
#: track's q is its class's times the running mean of its normalised innovation squared (NIS,
#: weight ``_NIS_WEIGHT``) over its expected value 2, kept within ``_Q_SCALE``: a target
#: driving straight is followed closely, one that manoeuvres widens its own filter.
_NIS_AFTER = 3
_NIS_WEIGHT = 0.3
_Q_SCALE = (0.5, 4.0)


class _Held:
    """One sensor frame being collected: its time, its detections so far and the largest
    ``frame_size`` they declare (0: none did)."""

    __slots__ = ("detections", "size", "time")

    def __init__(self, time: datetime) -> None:
        self.time = time
        self.detections: list[Detection] = []
        self.size = 0


@lru_cache(maxsize=4096)
def _support(frame: frozenset[str], name: str, confidence: float) -> MassFunction:
    return simple_support(frame, {name}, confidence)


def _canonical(d: Detection) -> tuple[float, float, float, str, float, str]:
    p = d.position
    return (p.lat_deg, p.lon_deg, d.sigma_h_m, d.object_class, d.confidence, d.event_id)


class Tracker:
    """Fuses detections into tracks; see the module docstring for the rules."""

    def __init__(self, settings: TrackerSettings | None = None) -> None:
        self.settings = s = settings or TrackerSettings()
        self.frame = frozenset(s.classes) | {OTHER}
        self.counts = TrackerCounts()
        self._tracks: dict[str, TrackState] = {}
        self._frames: dict[Source, _Held] = {}
        self._pending: set[str] = set()
        self._streaks: dict[tuple[str, str], int] = {}
        self._next = 0
        self._horizon_s = min(s.coast_after_s, s.max_gap_s, s.lost_after_s)
        self._index = TrackIndex(
            self._tracks, s.cell_m, self._horizon_s, exhaustive=s.index == "all_pairs"
        )
        self._qs: dict[str, float] = {}
        self._limits: dict[str, float] = {}
        self._gate2 = s.gate_sigma**2
        self._merge2 = s.merge_sigma**2

    def __len__(self) -> int:
        return len(self._tracks)

    @property
    def track_ids(self) -> list[str]:
        """The live tracks' ids (tentative ones included), oldest first."""
        return list(self._tracks)

    @property
    def confirmed_ids(self) -> list[str]:
        """The published (confirmed or coasting) tracks' ids, oldest first."""
        return [t for t, st in self._tracks.items() if st.stage != "tentative"]

    def stage(self, track_id: str) -> str:
        """``tentative``, ``confirmed`` or ``coasting``; ``KeyError`` if not live."""
        return self._tracks[track_id].stage

    # -- input -----------------------------------------------------------------------------

    def update(self, detection: Detection) -> list[Track]:
        """Add ``detection`` to its frame; the events of any frame this completes.

        A detection vaguer than ``max_sigma_m`` is refused and counted (``too_vague``): its
        gate would reach tracks kilometres away and keep them alive without placing them.
        """
        if not detection.sigma_h_m <= self.settings.max_sigma_m:
            self.counts.too_vague += 1
            return []
        source: Source = (detection.airframe, detection.sensor)
        out: list[Track] = []
        held = self._frames.get(source)
        if held is not None and held.time != detection.time:
            del self._frames[source]
            out += self._frame(held.detections)
            held = None
        if held is None:
            held = self._frames[source] = _Held(detection.time)
        held.detections.append(detection)
        if detection.frame_size is not None and detection.frame_size > held.size:
            held.size = detection.frame_size
        if len(held.detections) >= min(held.size or MAX_FRAME, MAX_FRAME):
            del self._frames[source]
            out += self._frame(held.detections)
        return out

    @property
    def holding(self) -> bool:
        """Whether a frame is held, waiting for more detections (``flush`` would process it)."""
        return bool(self._frames)

    def update_frame(self, detections: Iterable[Detection]) -> list[Track]:
        """Process ``detections`` now (grouped into frames), with every frame held before."""
        out: list[Track] = []
        for detection in detections:
            out += self.update(detection)
        return out + self.flush()

    def flush(self) -> list[Track]:
        """Process every frame still held, oldest first; the events they cause."""
        frames = sorted(
            self._frames.items(), key=lambda item: (item[1].time, item[0][0], item[0][1].value)
        )
        self._frames.clear()
        out: list[Track] = []
        for _, held in frames:
            out += self._frame(held.detections)
        return out

    def tick(self, now: datetime) -> list[Track]:
        """Flush frames, age tracks and send held-back updates at ``now``.

        Only tracks silent beyond the horizon are looked at (``tracking.index``): the cost
        does not grow with the tracks that are being seen.
        """
        s = self.settings
        out = self.flush()
        now_s = now.timestamp()
        self._expire(now_s)
        for track_id in self._index.wide:
            state = self._tracks[track_id]
            silent = now_s - state.updated_s
            if silent >= s.lost_after_s:
                self._drop(state)
                self.counts.lost += 1
                out.append(self._event(state, "lost", now))
            elif state.stage == "confirmed" and silent >= s.coast_after_s:
                state.stage = "coasting"
                self.counts.coasting += 1
        for track_id in sorted(self._pending):
            state = self._tracks[track_id]
            if now_s - state.emitted_s >= s.update_interval_s:
                self._pending.discard(track_id)
                out.append(self._emit(state, "updated", now_s))
        return out

    # -- one frame -------------------------------------------------------------------------

    def _frame(self, detections: list[Detection]) -> list[Track]:
        s = self.settings
        self.counts.frames += 1
        if len(detections) > 1:
            detections = sorted(detections, key=_canonical)
        first = detections[0]
        source: Source = (first.airframe, first.sensor)
        at_s = first.time.timestamp()
        self._expire(at_s)
        predicted: dict[str, Estimate] = {}
        near: set[str] = set()
        pairs: dict[tuple[int, int], float] = {}
        columns: dict[str, int] = {}
        fused: dict[tuple[int, int], tuple[MassFunction, float] | None] = {}
        innovations: dict[tuple[int, int], Innovation] = {}
        masses: list[MassFunction] = []
        examined = 0
        gate2 = self._gate2
        for i, d in enumerate(detections):
            if examined >= MAX_FRAME_PAIRS:
                self.counts.overload_refused += len(detections) - i
                detections = detections[:i]
                break
            name = d.object_class if d.object_class in self.frame else OTHER
            mass = _support(self.frame, name, d.confidence)
            masses.append(mass)
            sigma = max(d.sigma_h_m, MIN_SIGMA_M)
            r = sigma * sigma
            lat, lon = d.position.lat_deg, d.position.lon_deg
            conflicted = False
            widen = s.gate_sigma * sigma
            for track_id in self._candidates(lat, lon, sigma):
                examined += 1
                state = self._tracks[track_id]
                dt = at_s - state.updated_s
                if abs(dt) > s.max_gap_s:
                    continue
                east, north = offset_m(state.lat_deg, state.lon_deg, lat, lon)
                if math.hypot(east, north) > state.reach_m + widen and (
                    dt <= self._horizon_s or self._index.is_wide(track_id)
                ):
                    continue  # beyond this track's own reach: its gate cannot pass it
                estimate = predicted.get(track_id)
                if estimate is None:
                    estimate = predicted[track_id] = state.predicted(at_s, self._q(state))
                # The gate, written out (``Innovation.d2``); the pair's Innovation is built
                # only when it passes.
                x, p = estimate.x, estimate.p
                ye, yn = east - x[0], north - x[1]
                s00, s01, s11 = p[0] + r, p[1], p[5] + r
                det = s00 * s11 - s01 * s01
                if not (
                    det > 0.0 and s11 * ye * ye - 2.0 * s01 * ye * yn + s00 * yn * yn <= gate2 * det
                ):
                    continue
                innovation = Innovation(ye, yn, s00, s01, s11)
                near.add(track_id)
                try:
                    evidence = self._evidence(state, source, mass)
                except TotalConflict:
                    conflicted = True
                    continue
                key = (i, columns.setdefault(track_id, len(columns)))
                pairs[key] = innovation.cost
                fused[key] = evidence
                innovations[key] = innovation
            if conflicted:
                self.counts.total_conflict += 1
        ids = sorted(columns)  # canonical column order: the same whatever came first
        if len(ids) > 1:
            order = {track_id: n for n, track_id in enumerate(ids)}
            remap = {columns[t]: order[t] for t in ids}
            pairs = {(i, remap[j]): cost for (i, j), cost in pairs.items()}
            fused = {(i, remap[j]): ev for (i, j), ev in fused.items()}
            innovations = {(i, remap[j]): inn for (i, j), inn in innovations.items()}
        if len(detections) == 1:  # one row: the cheapest pair is the whole answer
            matched = {0: min(pairs, key=lambda ij: (pairs[ij], ij))[1]} if pairs else {}
        else:
            matched = assign(pairs)
        out: list[Track] = []
        hit: dict[str, bool] = {}  # track id → it was coasting before this frame
        for i, d in enumerate(detections):
            j = matched.get(i)
            if j is None:
                out += self._start(d, at_s, source, masses[i])
                continue
            state = self._tracks[ids[j]]
            evidence = fused[(i, j)]
            if evidence is not None:
                state.set_classes({**state.sources, source: masses[i]}, *evidence)
            self.counts.associated += 1
            hit[state.track_id] = self._hit(
                state, d, at_s, source, predicted[state.track_id], innovations[(i, j)]
            )
        for track_id, was_coasting in sorted(hit.items()):
            still = self._tracks.get(track_id)
            if still is None:
                continue  # folded into a track handled before it
            survivor, merged = self._merge(
                still, at_s, set(hit), near, predicted, was_coasting=was_coasting
            )
            out += merged + self._settled(survivor, at_s)
        for track_id in sorted(near - set(hit)):
            missed = self._tracks.get(track_id)
            if missed is not None and missed.stage == "tentative" and source in missed.seen_by:
                missed.chances += 1
                if missed.chances - missed.hits > s.confirm_window - s.confirm_hits:
                    self._drop(missed)
                    self.counts.discarded += 1
        return out

    def _evidence(
        self, state: TrackState, source: Source, mass: MassFunction
    ) -> tuple[MassFunction, float] | None:
        """The fused evidence if ``mass`` joined ``state`` (None: it would not change);
        raises ``TotalConflict``."""
        if state.sources.get(source) == mass:
            return None
        return fuse_sources({**state.sources, source: mass})

    def _q(self, state: TrackState) -> float:
        return self._class_q(state) * state.q_scale

    def _class_q(self, state: TrackState) -> float:
        q = self._qs.get(state.object_class)
        if q is None:
            # Time played X times faster: the white-noise acceleration's spectral density
            # q (m²/s³) is X³ larger, as velocities are X times and seconds 1/X as long.
            q = self._qs[state.object_class] = (
                self.settings.priors[state.object_class].q * self.settings.speed_scale**3
            )
        return q

    def _limit(self, name: str) -> float:
        limit = self._limits.get(name)
        if limit is None:
            limit = self._limits[name] = (
                self.settings.priors[name].max_speed_mps * self.settings.speed_scale
            )
        return limit

    # -- track life ------------------------------------------------------------------------

    def _hit(
        self,
        state: TrackState,
        d: Detection,
        at_s: float,
        source: Source,
        estimate: Estimate,
        innovation: Innovation,
    ) -> bool:
        """Fold ``d`` (``innovation`` against ``estimate``, the prediction to ``at_s``) into
        ``state``; whether the track was coasting before it."""
        s = self.settings
        was_coasting = state.stage == "coasting" or at_s - state.updated_s > s.coast_after_s
        estimate = estimate.copy()
        if state.hits >= _NIS_AFTER:
            state.nis += _NIS_WEIGHT * (min(innovation.d2, self._gate2) - state.nis)
            state.q_scale = min(_Q_SCALE[1], max(_Q_SCALE[0], state.nis / 2.0))
        estimate.update(innovation, POSITION)
        self._speed_prior(state, estimate)
        state.adopt(estimate, at_s)
        self._record(state, d, source)
        state.hits += 1
        state.chances += 1
        if state.stage == "coasting":
            state.stage = "confirmed"
        self._file(state)
        return was_coasting

    def _settled(self, state: TrackState, at_s: float) -> list[Track]:
        """After a frame: confirm a tentative track that has enough hits, or send an update."""
        s = self.settings
        if state.stage == "tentative" and state.hits >= s.confirm_hits:
            state.stage = "confirmed"
            self.counts.confirmed += 1
            return [self._emit(state, "created", at_s)]
        if state.stage != "tentative":
            return self._updated(state, at_s)
        return []

    def _speed_prior(self, state: TrackState, estimate: Estimate) -> None:
        limit = self._limit(state.object_class)
        east, north = estimate.x[2], estimate.x[3]
        speed = math.hypot(east, north)
        if speed <= limit:
            return
        self.counts.speed_prior += 1
        r = (self.settings.speed_prior_sigma * limit) ** 2
        # The speed along the estimate's course, not the velocity: the prior knows how fast
        # the class goes, not where to, so the course keeps its own uncertainty.
        estimate.update_speed(east / speed, north / speed, limit, r)

    def _record(self, state: TrackState, d: Detection, source: Source) -> None:
        if d.position.alt_msl_m is not None and d.time >= state.last_seen:
            state.alt_msl_m = d.position.alt_msl_m
        if d.subtype:
            name = d.object_class if d.object_class in self.frame else OTHER
            state.subtypes[name] = d.subtype
        state.detection_ids.append(d.event_id)
        state.detection_count += 1
        if d.origin_node is not None and d.origin_node not in state.nodes:
            state.add_nodes({d.origin_node})
        if source not in state.seen_by:
            state.airframes.add(d.airframe)
            state.sensors.add(d.sensor)
            state.seen_by.add(source)
        if d.time > state.last_seen:
            state.last_seen = d.time
        elif d.time < state.first_seen:
            state.first_seen = d.time

    def _start(self, d: Detection, at_s: float, source: Source, mass: MassFunction) -> list[Track]:
        s = self.settings
        if len(self._tracks) >= s.max_tracks:
            self.counts.refused_full += 1
            return []
        self._next += 1
        self.counts.created += 1
        best, belief = mass.best()
        sigma = max(d.sigma_h_m, MIN_SIGMA_M)
        state = TrackState(
            track_id=f"T-{BOOT_ID}-{self._next:04d}",
            serial=self._next,
            lat_deg=d.position.lat_deg,
            lon_deg=d.position.lon_deg,
            estimate=Estimate.at_rest(sigma, self._limit(best)),
            updated_s=at_s,
            first_seen=d.time,
            last_seen=d.time,
            sources={source: mass},
            classes=mass,
            object_class=best,
            confidence=belief,
        )
        self._record(state, d, source)
        self._tracks[state.track_id] = state
        self._file(state)
        if s.confirm_hits <= 1:
            state.stage = "confirmed"
            self.counts.confirmed += 1
            return [self._emit(state, "created", at_s)]
        return []

    def _drop(self, state: TrackState) -> None:
        del self._tracks[state.track_id]
        self._pending.discard(state.track_id)
        self._index.remove(state.track_id)
        for key in [k for k in self._streaks if state.track_id in k]:
            del self._streaks[key]

    # -- merge -----------------------------------------------------------------------------

    def _merge(
        self,
        state: TrackState,
        at_s: float,
        hit: set[str],
        near: set[str],
        predicted: dict[str, Estimate],
        *,
        was_coasting: bool,
    ) -> tuple[TrackState, list[Track]]:
        """Fold ``state`` and a twin together once they have agreed ``merge_after`` times.

        A twin is looked for among the tracks this frame's detections gated with (``near``,
        predicted to ``at_s`` in ``predicted``): a second track of the object the detection
        is of has it in its gate too. Two tracks that each took a detection of one frame are
        two objects (a frame sees an object once): never merged then.
        """
        s = self.settings
        if was_coasting or state.hits < 2 or len(near) < 2:
            return state, []  # a coasting estimate is too wide to tell two objects apart
        mine = state.estimate
        for other_id in sorted(near):
            other = self._tracks.get(other_id)
            if other is None or other is state or other.stage == "coasting":
                continue
            if min(state.hits, other.hits) < 2:
                continue  # nor is one fix with no velocity yet
            key = (
                (state.track_id, other_id)
                if state.track_id < other_id
                else (other_id, state.track_id)
            )
            if other_id in hit:
                if self._streaks:
                    self._streaks.pop(key, None)
                continue
            if abs(at_s - other.updated_s) > s.coast_after_s:
                continue
            theirs = predicted.get(other_id) or other.predicted(at_s, self._q(other))
            if not agree(state, other, theirs, self._merge2):
                self._streaks.pop(key, None)
                continue
            evidence = {**other.sources, **state.sources}  # state holds the newest report
            try:
                combined, k = fuse_sources(evidence)
            except TotalConflict:
                continue
            streak = self._streaks[key] = self._streaks.get(key, 0) + 1
            if streak < s.merge_after:
                continue
            del self._streaks[key]
            old, young = elder(state, other)
            old.set_classes(evidence, combined, k)
            young_estimate = theirs if young is other else mine.copy()
            base = old.estimate if old is state else theirs.copy()
            fold(old, base, young, young_estimate, at_s)
            self._drop(young)
            self._file(old)
            self.counts.merged += 1
            old.emitted_class = ""  # its picture changed: the next update goes out at once
            if young.stage == "tentative":
                return old, []
            return old, [self._event(young, "merged", old.last_seen, merged_into=old.track_id)]
        return state, []

    # -- index -----------------------------------------------------------------------------

    def _reach_of(self, state: TrackState, horizon_s: float | None = None) -> float:
        """How far from its filed position a detection the gate passes could lie within
        ``horizon_s`` of its update (the fresh horizon, ``coast_after_s``, by default; the
        gate's width is convex in Δt, so the horizon's ends bound it), less the detection's
        own σ (the query adds it)."""
        s = self.settings
        horizon = self._horizon_s if horizon_s is None else horizon_s
        later = state.estimate.position_var_max_after(horizon, self._q(state))
        widest = max(state.estimate.position_var_max, later)
        return s.gate_sigma * math.sqrt(max(widest, 0.0)) + state.speed_mps * horizon

    def _file(self, state: TrackState) -> None:
        state.reach_m = self._reach_of(state)
        self._index.file(state)

    def _expire(self, at_s: float) -> None:
        """Tracks silent beyond the horizon at ``at_s``: a tentative one is dropped, a
        confirmed one coasts, its reach now spanning all the time it may still take a
        detection."""
        for track_id in self._index.expire(at_s):
            state = self._tracks[track_id]
            if state.stage == "tentative":
                self._drop(state)
                self.counts.discarded += 1
                continue
            if state.stage == "confirmed" and at_s - state.updated_s >= self.settings.coast_after_s:
                state.stage = "coasting"
                self.counts.coasting += 1
            state.reach_m = self._reach_of(state, self.settings.max_gap_s)

    def _candidates(self, lat: float, lon: float, sigma_m: float) -> list[str]:
        return self._index.candidates(lat, lon, self.settings.gate_sigma * sigma_m)

    # -- emission --------------------------------------------------------------------------

    def _updated(self, state: TrackState, at_s: float) -> list[Track]:
        is_due = at_s - state.emitted_s >= self.settings.update_interval_s
        if state.object_class != state.emitted_class or is_due or self._drifted(state, at_s):
            self._pending.discard(state.track_id)
            return [self._emit(state, "updated", at_s)]
        self._pending.add(state.track_id)
        return []

    def _drifted(self, state: TrackState, at_s: float) -> bool:
        """Whether receivers, dead-reckoning the last event, now show the track further from
        its estimate than ``max_drift_m`` and than the estimate's own σ (a shift within its
        uncertainty is not news), or 2σ while the last event carried no velocity (the
        estimate's own wander is largest then)."""
        if state.shown is None:
            return True
        lat, lon, ve, vn, shown_s = state.shown
        dt = at_s - shown_s
        east, north = offset_m(lat, lon, state.lat_deg, state.lon_deg)
        drift = math.hypot(east - ve * dt, north - vn * dt)
        without_velocity = ve == 0.0 and vn == 0.0
        return drift > max(
            self.settings.max_drift_m, (2.0 if without_velocity else 1.0) * state.sigma_m
        )

    def _emit(self, state: TrackState, status: Status, at_s: float) -> Track:
        state.emitted_s = max(state.emitted_s, at_s)
        state.emitted_class = state.object_class
        return self._event(state, status, state.last_seen)

    def _event(
        self, state: TrackState, status: Status, when: datetime, merged_into: str | None = None
    ) -> Track:
        s = self.settings
        return track_event(
            state,
            status,
            when,
            hostile_classes=s.hostile_classes,
            loitering_munition=s.loitering_munition,
            report_velocity_sigma_mps=s.report_velocity_sigma_mps * s.speed_scale,
            merged_into=merged_into,
        )
