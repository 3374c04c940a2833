"""Two tracks of one object: when they agree, and how the younger is folded into the elder.

``agree`` tests a track's estimate against another's predicted to the same time: the position
difference and the velocity difference each within ``merge_sigma`` (squared: ``limit2``)
Mahalanobis distance, using both covariances. ``elder`` picks the survivor: a published track
outlives a tentative one, else the older. ``fold`` takes the younger estimate's position into
the survivor's as one more measurement (its covariance as the measurement's) and keeps its
detections, airframes, sensors and subtypes.
"""

from __future__ import annotations

import math

from gateway.flow.localplane import displace, offset_m
from tracking.kalman import POSITION, Estimate
from tracking.track import TrackState

__all__ = ["agree", "elder", "fold"]


def _d2(ye: float, yn: float, s00: float, s01: float, s11: float) -> float:
    det = s00 * s11 - s01 * s01
    if not det > 0.0:
        return math.inf
    return (s11 * ye * ye - 2.0 * s01 * ye * yn + s00 * yn * yn) / det


def agree(state: TrackState, other: TrackState, theirs: Estimate, limit2: float) -> bool:
    """Whether ``state``'s estimate and ``other``'s (``theirs``, predicted to the time of
    ``state``'s) agree in position and in velocity within ``limit2`` (d²)."""
    mine = state.estimate
    position = other.innovation(theirs, state.lat_deg, state.lon_deg, 0.0)
    close = position.s00 + mine.p[0], position.s01 + mine.p[1], position.s11 + mine.p[5]
    if _d2(position.ye, position.yn, *close) > limit2:
        return False
    ve, vn = mine.x[2] - theirs.x[2], mine.x[3] - theirs.x[3]
    vel = (mine.p[10] + theirs.p[10], mine.p[11] + theirs.p[11], mine.p[15] + theirs.p[15])
    return _d2(ve, vn, *vel) <= limit2


def elder(a: TrackState, b: TrackState) -> tuple[TrackState, TrackState]:
    """(survivor, folded): a published track outlives a tentative one, else the older."""
    a_rank = (a.stage == "tentative", a.serial)
    b_rank = (b.stage == "tentative", b.serial)
    return (a, b) if a_rank < b_rank else (b, a)


def fold(
    old: TrackState, base: Estimate, young: TrackState, young_estimate: Estimate, at_s: float
) -> None:
    """Take ``young`` (its estimate ``young_estimate`` at ``at_s``) into ``old`` (``base``)."""
    lat, lon = displace(young.lat_deg, young.lon_deg, *young_estimate.x[:2])
    east, north = offset_m(old.lat_deg, old.lon_deg, lat, lon)
    p = young_estimate.p
    base.update(base.innovation(east, north, p[0], p[1], p[5], POSITION), POSITION)
    old.adopt(base, at_s)
    for name, subtype in young.subtypes.items():
        old.subtypes.setdefault(name, subtype)
    old.detection_ids.extend(young.detection_ids)
    old.detection_count += young.detection_count
    old.airframes |= young.airframes
    old.add_nodes(young.nodes)
    old.sensors |= young.sensors
    old.seen_by |= young.seen_by
    old.hits += young.hits
    old.first_seen = min(old.first_seen, young.first_seen)
    if young.last_seen > old.last_seen:
        old.last_seen = young.last_seen
        old.alt_msl_m = young.alt_msl_m if young.alt_msl_m is not None else old.alt_msl_m
