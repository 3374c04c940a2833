"""A track's state as the ``Track`` event the bus carries.

Every event of one track carries a strictly newer ``time`` than the one before it (CoT, NFFI
and SLB receivers keep the newest time per uid): the newest detection's time, or the moment of
the loss or merge, moved on by a millisecond when it would not be newer. The velocity is
published only once the filter's velocity σ per axis is at most ``report_velocity_sigma_mps``
plus 6 % of the speed (then its p90 error is within about 2 m/s + 10 %):
a speed from two fixes is noise, and a C2 net must not hear it as a tank doing 250 km/h.
"""

from __future__ import annotations

import math
from datetime import datetime, timedelta
from functools import cache
from typing import Literal, TypeVar

from gateway.domain.sidc import Hostility, symbol_codes
from gateway.domain.targeting import CEP50_FACTOR, CEP90_FACTOR
from gateway.events import Position, Sensor, Track, Velocity
from tracking.track import TrackState

__all__ = ["Status", "track_event"]

T = TypeVar("T", str, Sensor)

Status = Literal["created", "updated", "lost", "merged"]

#: How far a time is moved on to be strictly newer than the track's last.
_STEP = timedelta(milliseconds=1)


@cache
def _sidc(object_class: str, hostility: Hostility, loitering_munition: str) -> str | None:
    variant: Literal["uav_attack", "missile"] = (
        "missile" if loitering_munition == "missile" else "uav_attack"
    )
    try:
        return symbol_codes(object_class, hostility, loitering_munition=variant).sidc_2525c
    except KeyError:
        return None  # "other" and classes the symbol table lacks: the sink picks a generic one


def _stamp(state: TrackState, when: datetime) -> datetime:
    if state.published is not None and when <= state.published:
        when = state.published + _STEP
    state.published = when
    return when


def track_event(
    state: TrackState,
    status: Status,
    when: datetime,
    *,
    hostile_classes: frozenset[str],
    loitering_munition: str,
    report_velocity_sigma_mps: float,
    merged_into: str | None = None,
) -> Track:
    """The ``Track`` event of ``state`` with ``status`` at (about) ``when``."""
    state.sequence += 1
    hostility: Hostility = "hostile" if state.object_class in hostile_classes else "suspect"
    velocity = speed = course = None
    east, north = state.velocity
    now_speed = math.hypot(east, north)
    if state.estimate.velocity_sigma <= report_velocity_sigma_mps + 0.06 * now_speed:
        velocity = Velocity(north_mps=north, east_mps=east, down_mps=0.0)
        speed, course = now_speed, state.course_deg
    sigma = state.sigma_m  # ≥ 0: a square root
    shown_v = (east, north) if velocity is not None else (0.0, 0.0)
    state.shown = (state.lat_deg, state.lon_deg, *shown_v, state.updated_s)
    return Track(
        event_id=f"{state.track_id}-{state.sequence}",  # gateway.events.event_id's form
        track_id=state.track_id,
        time=_stamp(state, when),
        status=status,
        merged_into=merged_into,
        object_class=state.object_class,
        subtype=state.subtypes.get(state.object_class, ""),
        confidence=state.confidence,
        class_conflict=state.class_conflict,
        position=Position(lat_deg=state.lat_deg, lon_deg=state.lon_deg, alt_msl_m=state.alt_msl_m),
        cep50_m=CEP50_FACTOR * sigma,
        cep90_m=CEP90_FACTOR * sigma,
        velocity=velocity,
        speed_mps=speed,
        course_deg=course,
        detection_ids=tuple(state.detection_ids),
        detection_count=state.detection_count,
        airframes=_sorted(state.airframes),
        origin_nodes=_sorted(state.nodes),
        sensors=_sorted(state.sensors),
        first_seen=state.first_seen,
        last_seen=state.last_seen,
        hostility=hostility,
        sidc=_sidc(state.object_class, hostility, loitering_munition),
    )


def _sorted(items: set[T]) -> tuple[T, ...]:
    return (next(iter(items)),) if len(items) == 1 else tuple(sorted(items))
