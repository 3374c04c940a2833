"""MAVLink messages to typed events: the per-airframe state that merges the latest fields.

This is the one place where values from the wire are checked: MAVLink's "unknown" sentinels
(-1, UINT16_MAX, 0 for optional extensions, NaN) become None, units become SI, and a position
of exactly 0,0 (an autopilot without a fix) becomes no position. After this, events are trusted.

Because the checks are made here, on values the decoder already typed, no event is validated a
second time by pydantic: Telemetry and Detection are built with ``events.checked``, and the
small models inside them (Position, Velocity, Attitude) by ``position``, ``velocity`` and
``attitude`` below, after the checks their fields declare (latitude and longitude in range,
altitudes plausible, angles finite) were made by hand. A latitude or longitude out of range
goes to the validating constructor, which refuses it as it always did (the message counts as
a handler error and changes nothing). tests/gateway/fleet/test_normalise.py holds the fast
path equal to validation on generated messages.

Telemetry is latest-wins and under load many messages are merged into one snapshot, so the
state keeps the checked values of the latest position, velocity and attitude and builds their
models only when a snapshot (or ``field``) needs them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from gateway.clock import Clock
from gateway.domain.energy import EnergyProfile, EwMode, endurance_remaining_min
from gateway.domain.terrain import TerrainModel, agl_from_msl, agl_sigma
from gateway.events import (
    ALT_MAX_M,
    BOOT_ID,
    Attitude,
    Detection,
    Position,
    Sensor,
    Telemetry,
    Velocity,
    checked,
    checked_fields,
    checked_template,
    event_id,
    plausible_alt,
)
from gateway.fleet.dialect import CLASS_NAMES, SENSOR_NAMES
from gateway.fleet.mavlink import MavMessage

__all__ = ["NORMALISED_TYPES", "AirframeState", "Enrichment", "detection_from"]


@dataclass(frozen=True)
class Enrichment:
    """What the platform maths adds to an airframe's telemetry."""

    energy: EnergyProfile
    ew_mode: EwMode
    terrain: TerrainModel | None = None
    baro_sigma_m: float = 0.5


_UINT16_MAX = 0xFFFF
_MAV_AUTOPILOT_INVALID = 8
_MAV_MODE_FLAG_SAFETY_ARMED = 128

#: The MAVLink messages that change an airframe's Telemetry.
NORMALISED_TYPES = frozenset(
    {
        "HEARTBEAT",
        "SYS_STATUS",
        "GLOBAL_POSITION_INT",
        "GPS_RAW_INT",
        "ATTITUDE",
        "VFR_HUD",
        "BATTERY_STATUS",
    }
)


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


_INF = math.inf
_POSITION_FIELDS = frozenset(Position.model_fields)
_VELOCITY_FIELDS = frozenset(Velocity.model_fields)
_ATTITUDE_FIELDS = frozenset(Attitude.model_fields)


def position(
    lat_deg: float,
    lon_deg: float,
    alt_msl_m: float | None,
    alt_hae_m: float | None,
    alt_rel_home_m: float | None,
) -> Position:
    """The Position of checked values (floats in the ranges Position declares), unvalidated.

    Equal to ``Position(...)`` given every field: the same values, fields set and JSON.
    """
    values = {
        "lat_deg": lat_deg,
        "lon_deg": lon_deg,
        "alt_msl_m": alt_msl_m,
        "alt_hae_m": alt_hae_m,
        "alt_rel_home_m": alt_rel_home_m,
    }
    return checked_fields(Position, values, set(_POSITION_FIELDS))


def velocity(north_mps: float, east_mps: float, down_mps: float) -> Velocity:
    """The Velocity of three floats, unvalidated (equal to ``Velocity(...)``)."""
    values = {"north_mps": north_mps, "east_mps": east_mps, "down_mps": down_mps}
    return checked_fields(Velocity, values, set(_VELOCITY_FIELDS))


def attitude(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Attitude:
    """The Attitude of three floats, unvalidated (equal to ``Attitude(...)``)."""
    values = {"roll_rad": roll_rad, "pitch_rad": pitch_rad, "yaw_rad": yaw_rad}
    return checked_fields(Attitude, values, set(_ATTITUDE_FIELDS))


class AirframeState:
    """The merged latest state of one airframe, and the Telemetry it yields.

    ``apply`` takes one message of a type in ``NORMALISED_TYPES`` and returns a fresh
    Telemetry snapshot; the state is only ever read and written from the event loop.
    """

    def __init__(self, airframe: str, clock: Clock, enrichment: Enrichment | None = None) -> None:
        self.airframe = airframe
        self._clock = clock
        self._enrichment = enrichment
        #: The EW mode's value, read once (an enum's ``value`` is a descriptor call).
        self._ew_mode = None if enrichment is None else enrichment.ew_mode.value
        self._agl_for: tuple[float, float, float | None] | None = None
        self._agl: tuple[float | None, float | None] = (None, None)
        self._seq = 0
        #: ``event_id(airframe, "tel", BOOT_ID, n)`` is this prefix and n.
        self._id_prefix = event_id(airframe, "tel", BOOT_ID, "")
        self._endurance: tuple[float | None, float | None] = (None, None)
        self._fields: dict[str, Any] = {}
        #: Every Telemetry field with its default, the airframe's in: a snapshot's start.
        self._template = {**checked_template(Telemetry), "airframe": airframe}
        self._geoid_sep_m: float | None = None
        #: The checked values of the latest position, velocity and attitude whose models are
        #: not built yet (``_settle`` builds them); None when ``_fields`` holds the latest.
        self._position_values: (
            tuple[float, float, float | None, float | None, float | None] | None
        ) = None
        self._velocity_values: tuple[float, float, float] | None = None
        self._attitude_values: tuple[float, float, float] | None = None
        self._handlers: dict[str, Callable[[MavMessage], bool]] = {
            "HEARTBEAT": self._heartbeat,
            "SYS_STATUS": self._sys_status,
            "GLOBAL_POSITION_INT": self._global_position,
            "GPS_RAW_INT": self._gps_raw,
            "ATTITUDE": self._attitude,
            "VFR_HUD": self._vfr_hud,
            "BATTERY_STATUS": self._battery_status,
        }
        self.active_link: str | None = None

    def set_active_link(self, label: str | None) -> None:
        """Record which link is active; later snapshots carry it."""
        self.active_link = label

    def updater(self, name: str) -> Callable[[MavMessage], bool]:
        """The ``update`` of messages of type ``name`` alone (one of ``NORMALISED_TYPES``)."""
        return self._handlers[name]

    def update(self, name: str, msg: MavMessage) -> bool:
        """Merge ``msg`` (of type ``name``); True if the state changed."""
        handler = self._handlers.get(name)
        return handler is not None and handler(msg)

    def field(self, name: str) -> Any:
        """The latest merged value of one Telemetry field (None if never reported)."""
        self._settle()
        return self._fields.get(name)

    def _settle(self) -> None:
        """Build the models of the values merged since the last snapshot."""
        f = self._fields
        if self._position_values is not None:
            f["position"] = position(*self._position_values)
            self._position_values = None
        if self._velocity_values is not None:
            f["velocity"] = velocity(*self._velocity_values)
            self._velocity_values = None
        if self._attitude_values is not None:
            f["attitude"] = attitude(*self._attitude_values)
            self._attitude_values = None

    def snapshot(self, now: datetime | None = None) -> Telemetry:
        """The merged state now, as a new Telemetry event (made at ``now``, else the clock's
        time: a caller that makes many at once reads the clock once)."""
        self._seq += 1
        self._settle()
        merged = self._fields
        fields = self._template.copy()  # declaration order, which the JSON keeps
        fields.update(merged)
        fields["event_id"] = f"{self._id_prefix}{self._seq}"
        fields["time"] = self._clock() if now is None else now
        fields["active_link"] = self.active_link
        given = {"event_id", "airframe", "time", "active_link", *merged}
        if self._enrichment is not None:
            self._derive(self._enrichment, fields, given)
        # Every field was checked when it was merged (the update handlers, ``_derive``).
        return checked_fields(Telemetry, fields, given)

    def _derive(self, enrichment: Enrichment, out: dict[str, Any], given: set[str]) -> None:
        """Height above ground (where a DEM covers the point) and predicted endurance, into
        ``out``, their names into ``given``."""
        out["ew_mode"] = self._ew_mode
        given.add("ew_mode")
        position: Position | None = self._fields.get("position")
        terrain = enrichment.terrain
        if position is not None and position.alt_msl_m is not None and terrain is not None:
            key = (position.lat_deg, position.lon_deg, position.alt_msl_m)
            if key != self._agl_for:
                # Tile lookups are memory-mapped reads; only a moved airframe pays for one.
                self._agl_for = key
                found = terrain.lookup(position.lat_deg, position.lon_deg)
                self._agl = (
                    (None, None)
                    if found is None
                    else (
                        agl_from_msl(position.alt_msl_m, found[0]),
                        agl_sigma(enrichment.baro_sigma_m, found[1].sigma_m),
                    )
                )
            out["alt_agl_m"], out["agl_sigma_m"] = self._agl
            given.update(("alt_agl_m", "agl_sigma_m"))
        profile = enrichment.energy
        pct = self._fields.get("battery_pct")
        consumed = self._fields.get("battery_consumed_wh")
        wh_left = None
        if pct is not None:
            wh_left = profile.battery_usable_wh * pct / 100.0
        elif consumed is not None:
            wh_left = profile.battery_usable_wh - consumed
        if wh_left is not None:
            if self._endurance[0] != wh_left:  # the battery changes far less often than this runs
                # No solar measurement arrives over MAVLink: predict the worst case (night).
                minutes = endurance_remaining_min(wh_left, profile, enrichment.ew_mode)
                self._endurance = (wh_left, minutes)
            out["endurance_remaining_min"] = self._endurance[1]
            given.add("endurance_remaining_min")

    def apply(self, name: str, msg: MavMessage) -> Telemetry | None:
        """``update`` then ``snapshot``; None if the message changed nothing."""
        return self.snapshot() if self.update(name, msg) else None

    def _heartbeat(self, msg: MavMessage) -> bool:
        # Ground stations and companion computers send heartbeats under the same sysid;
        # only the autopilot's describes the vehicle.
        if msg.autopilot == _MAV_AUTOPILOT_INVALID:
            return False
        f = self._fields
        f["mav_type"] = msg.type
        f["autopilot"] = msg.autopilot
        f["is_armed"] = bool(msg.base_mode & _MAV_MODE_FLAG_SAFETY_ARMED)
        f["custom_mode"] = msg.custom_mode
        f["system_status"] = msg.system_status
        return True

    def _sys_status(self, msg: MavMessage) -> bool:
        f = self._fields
        f["battery_voltage_v"] = (
            None if msg.voltage_battery == _UINT16_MAX else msg.voltage_battery / 1000.0
        )
        f["battery_current_a"] = None if msg.current_battery == -1 else msg.current_battery / 100.0
        f["battery_pct"] = None if msg.battery_remaining < 0 else float(msg.battery_remaining)
        return True

    def _global_position(self, msg: MavMessage) -> bool:
        f = self._fields
        lat_e7, lon_e7 = msg.lat, msg.lon  # each field read once: this runs per message
        if lat_e7 == 0 and lon_e7 == 0:
            f["position"] = None
            self._position_values = None
        else:
            lat, lon = lat_e7 / 1e7, lon_e7 / 1e7
            alt_msl_m = plausible_alt(msg.alt / 1000.0)
            sep = self._geoid_sep_m
            alt_hae_m = None if sep is None or alt_msl_m is None else plausible_alt(alt_msl_m + sep)
            rel = msg.relative_alt / 1000.0
            alt_rel_home_m = rel if -ALT_MAX_M <= rel <= ALT_MAX_M else None
            if -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0:  # NaN compares False
                self._position_values = (lat, lon, alt_msl_m, alt_hae_m, alt_rel_home_m)
            else:
                # Outside the ranges Position declares: its validation refuses the message
                # (raises, so nothing of it is merged), as it always has.
                f["position"] = Position(
                    lat_deg=lat,
                    lon_deg=lon,
                    alt_msl_m=alt_msl_m,
                    alt_hae_m=alt_hae_m,
                    alt_rel_home_m=alt_rel_home_m,
                )
                self._position_values = None
        self._velocity_values = (msg.vx / 100.0, msg.vy / 100.0, msg.vz / 100.0)
        hdg = msg.hdg
        if hdg != _UINT16_MAX:
            f["heading_deg"] = hdg / 100.0
        return True

    def _gps_raw(self, msg: MavMessage) -> bool:
        f = self._fields
        f["gps_fix_type"] = msg.fix_type
        f["satellites_visible"] = None if msg.satellites_visible == 255 else msg.satellites_visible
        # alt_ellipsoid and h_acc are MAVLink 2 extensions: absent (0) from MAVLink 1 senders.
        alt_ellipsoid = getattr(msg, "alt_ellipsoid", 0)
        if alt_ellipsoid and msg.fix_type >= 3:
            self._geoid_sep_m = (alt_ellipsoid - msg.alt) / 1000.0
        h_acc = getattr(msg, "h_acc", 0)
        f["h_acc_m"] = h_acc / 1000.0 if h_acc else None
        return True

    def _attitude(self, msg: MavMessage) -> bool:
        roll, pitch, yaw = msg.roll, msg.pitch, msg.yaw
        # Finite angles only (NaN and the infinities compare False).
        if not (-_INF < roll < _INF and -_INF < pitch < _INF and -_INF < yaw < _INF):
            return False
        self._attitude_values = (float(roll), float(pitch), float(yaw))
        return True

    def _vfr_hud(self, msg: MavMessage) -> bool:
        f = self._fields
        f["airspeed_mps"] = _finite(msg.airspeed)
        f["groundspeed_mps"] = _finite(msg.groundspeed)
        f["climb_mps"] = _finite(msg.climb)
        return True

    def _battery_status(self, msg: MavMessage) -> bool:
        f = self._fields
        if msg.battery_remaining >= 0:
            f["battery_pct"] = float(msg.battery_remaining)
        if msg.current_battery != -1:
            f["battery_current_a"] = msg.current_battery / 100.0
        # energy_consumed is in hectojoules: 1 hJ = 100 J = 1/36 Wh.
        f["battery_consumed_wh"] = (
            None if msg.energy_consumed == -1 else msg.energy_consumed * 100.0 / 3600.0
        )
        time_remaining = getattr(msg, "time_remaining", 0)
        f["battery_time_remaining_s"] = float(time_remaining) if time_remaining else None
        return True


_DAY_US = 86_400_000_000
#: A horizontal σ beyond this is no position at all (and would widen fusion's search for all).
MAX_SIGMA_M = 10_000.0
#: An observation time ahead of ours by more than this is not believed (clock skew allows a
#: little): a detection dated hours ahead would keep its track from ever ageing out.
_AHEAD_US = 60_000_000


def detection_from(airframe: str, msg: MavMessage, now: datetime) -> Detection | None:
    """A Detection from a FISCHER_DETECTION message; None if its values are not physical.

    The observation time is the airframe's ``time_usec`` when it is at most a day behind ours
    or a minute ahead (airframes have GPS time), else our receive time.
    """
    lat, lon = msg.lat / 1e7, msg.lon / 1e7
    sigma = msg.sigma_h
    sensor = SENSOR_NAMES.get(msg.sensor)
    if (
        not (-90 <= lat <= 90 and -180 <= lon <= 180)
        or (msg.lat == 0 and msg.lon == 0)
        or not math.isfinite(sigma)
        or not 0 <= sigma <= MAX_SIGMA_M
        or sensor is None
        or msg.confidence > 100
    ):
        return None
    observed = now
    now_us = int(now.timestamp() * 1_000_000)
    ahead_us = msg.time_usec - now_us
    if -_DAY_US <= ahead_us <= _AHEAD_US:
        observed = now + timedelta(microseconds=ahead_us)
    subtype = msg.subtype.decode("ascii", "replace") if isinstance(msg.subtype, bytes) else ""
    # Every value was checked above (the ranges pydantic would check included): no validation.
    return checked(
        Detection,
        event_id=event_id(airframe, "det", msg.detection_id, msg.time_usec),
        airframe=airframe,
        time=observed,
        sensor=Sensor(sensor),
        object_class=CLASS_NAMES.get(msg.class_id, f"class_{msg.class_id}"),
        subtype=subtype,
        confidence=msg.confidence / 100.0,
        position=Position(
            lat_deg=lat,
            lon_deg=lon,
            alt_msl_m=plausible_alt(msg.alt_msl),
        ),
        sigma_h_m=float(sigma),
        frame_size=msg.frame_size or None,
    )
