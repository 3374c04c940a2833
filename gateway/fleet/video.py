"""Camera and gimbal MAVLink to ``VideoFrameMetadata``: what each airframe's camera sees.

``CameraView`` keeps the latest CAMERA_FOV_STATUS and GIMBAL_DEVICE_ATTITUDE_STATUS of one
airframe and, with its telemetry (``AirframeState``), builds a ``VideoFrameMetadata`` for
every CAMERA_FOV_STATUS, and for a gimbal report when no camera report came in the last
``CAMERA_QUIET_S`` (a gimbal without a MAVLink camera). Ingest registers both handlers on
the airframe session's message table.

Pointing comes from the camera's own attitude quaternion when it sends one, else from the
gimbal's (yaw in the vehicle or the earth frame, per its flags) and the platform heading.
The frame centre is the camera's ``lat_image``/``lon_image`` when it reports them, else the
optical axis is intersected with the terrain (the DEM, or flat ground at the home altitude
where no tile covers it) by ``gateway.domain.lookat``. Values MAVLink marks unknown (INT32_MAX,
NaN) are None; an airframe without a position yields nothing.
"""

from __future__ import annotations

import math
import time
from typing import Any

from gateway.clock import Clock
from gateway.domain.geodesy import distance_bearing
from gateway.domain.lookat import (
    flat_intersection,
    footprint_width_m,
    ground_intersection,
    quaternion_to_euler,
    relative_pointing,
)
from gateway.domain.terrain import TerrainModel
from gateway.events import (
    BOOT_ID,
    Attitude,
    Position,
    VideoFrameMetadata,
    event_id,
    plausible_alt,
)
from gateway.fleet.mavlink import MavMessage
from gateway.fleet.normalise import AirframeState

__all__ = ["CAMERA_MESSAGES", "CAMERA_QUIET_S", "CameraView"]

#: The MAVLink messages a ``CameraView`` takes.
CAMERA_MESSAGES = ("CAMERA_FOV_STATUS", "GIMBAL_DEVICE_ATTITUDE_STATUS")
#: A gimbal report yields an event only when no camera report came for this long.
CAMERA_QUIET_S = 1.0

_INT32_MAX = 0x7FFFFFFF
_YAW_LOCK = 16  # GIMBAL_DEVICE_FLAGS_YAW_LOCK: yaw absolute (older firmware's earth frame)
_YAW_IN_VEHICLE_FRAME = 32
_YAW_IN_EARTH_FRAME = 64


def _quaternion(q: Any) -> tuple[float, float, float, float] | None:
    try:
        w, x, y, z = (float(v) for v in q)
    except (TypeError, ValueError):
        return None
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(norm) or norm < 1e-6:
        return None
    return w / norm, x / norm, y / norm, z / norm


def _degrees_e7(value: int) -> float | None:
    return None if value == _INT32_MAX else value / 1e7


def _fov(value: float) -> float | None:
    return value if math.isfinite(value) and 0 < value <= 180 else None


class CameraView:
    """One airframe's camera and gimbal state; see the module docstring."""

    def __init__(
        self,
        airframe: str,
        state: AirframeState,
        clock: Clock,
        terrain: TerrainModel | None = None,
    ) -> None:
        self.airframe = airframe
        self._state = state
        self._clock = clock
        self._terrain = terrain
        self._seq = 0
        self._camera: MavMessage | None = None
        self._camera_mono = -math.inf
        self._gimbal: tuple[float, float, float, bool] | None = None  # roll, pitch, yaw, earth

    def camera_fov(self, msg: MavMessage) -> VideoFrameMetadata | None:
        """Take a CAMERA_FOV_STATUS; the frame's metadata, or None without a position."""
        self._camera = msg
        self._camera_mono = time.monotonic()
        return self.build()

    def gimbal_attitude(self, msg: MavMessage) -> VideoFrameMetadata | None:
        """Take a GIMBAL_DEVICE_ATTITUDE_STATUS; metadata only when the camera is quiet."""
        q = _quaternion(msg.q)
        if q is None:
            return None
        flags = int(msg.flags)
        earth = bool(flags & _YAW_IN_EARTH_FRAME) or (
            bool(flags & _YAW_LOCK) and not flags & _YAW_IN_VEHICLE_FRAME
        )
        self._gimbal = (*quaternion_to_euler(*q), earth)
        if time.monotonic() - self._camera_mono < CAMERA_QUIET_S:
            return None
        return self.build()

    def _ground(self, lat: float, lon: float) -> float | None:
        return None if self._terrain is None else self._terrain.ground_elevation_m(lat, lon)

    def _pointing(self, attitude: Attitude | None, heading_deg: float | None) -> tuple[
        float, float, float] | None:  # fmt: skip
        """(absolute azimuth, elevation, roll) of the optical axis in degrees, if known."""
        cam = self._camera
        q = None if cam is None else _quaternion(cam.q)
        if q is not None:
            roll, pitch, yaw = quaternion_to_euler(*q)
            return _wrap(math.degrees(yaw)), math.degrees(pitch), math.degrees(roll)
        if self._gimbal is None:
            return None
        roll, pitch, yaw, earth = self._gimbal
        yaw_deg = math.degrees(yaw)
        if not earth:
            base = heading_deg
            if base is None and attitude is not None:
                base = math.degrees(attitude.yaw_rad)
            if base is None:
                return None
            yaw_deg += base
        return _wrap(yaw_deg), math.degrees(pitch), math.degrees(roll)

    def build(self) -> VideoFrameMetadata | None:
        """The metadata of the current frame from everything known now."""
        state = self._state
        position: Position | None = state.field("position")
        cam = self._camera
        sensor = position
        if cam is not None:
            lat, lon = _degrees_e7(int(cam.lat_camera)), _degrees_e7(int(cam.lon_camera))
            if lat is not None and lon is not None and -90 <= lat <= 90 and -180 <= lon <= 180:
                alt = (
                    None
                    if int(cam.alt_camera) == _INT32_MAX
                    else plausible_alt(cam.alt_camera / 1000.0)
                )
                sensor = Position(lat_deg=lat, lon_deg=lon, alt_msl_m=alt)
        if sensor is None:
            return None
        attitude: Attitude | None = state.field("attitude")
        heading = state.field("heading_deg")
        if heading is None and attitude is not None:
            heading = _wrap(math.degrees(attitude.yaw_rad))
        home = None
        if position is not None and None not in (position.alt_msl_m, position.alt_rel_home_m):
            home = position.alt_msl_m - position.alt_rel_home_m  # type: ignore[operator]
        pointing = self._pointing(attitude, heading)
        fields: dict[str, Any] = {}
        if pointing is not None:
            azimuth, elevation, cam_roll = pointing
            if attitude is not None:
                rel = relative_pointing(
                    attitude.roll_rad, attitude.pitch_rad, attitude.yaw_rad, azimuth, elevation
                )
            elif heading is not None:
                rel = (_wrap(azimuth - heading), elevation)
            else:
                rel = None
            if rel is not None:
                fields["sensor_azimuth_deg"] = _wrap(rel[0])
                fields["sensor_elevation_deg"] = rel[1]
                fields["sensor_roll_deg"] = _wrap(cam_roll)
        hfov = None if cam is None else _fov(float(cam.hfov))
        vfov = None if cam is None else _fov(float(cam.vfov))
        self._frame_centre(fields, sensor, pointing, home)
        if hfov is not None and fields.get("slant_range_m") is not None:
            fields["target_width_m"] = footprint_width_m(fields["slant_range_m"], hfov)
        alt_agl = None
        if sensor.alt_msl_m is not None:
            ground = self._ground(sensor.lat_deg, sensor.lon_deg)
            ground = home if ground is None else ground
            alt_agl = None if ground is None else sensor.alt_msl_m - ground
        if heading is not None:
            heading = _wrap(heading)
        self._seq += 1
        return VideoFrameMetadata(
            event_id=event_id(self.airframe, "vfm", BOOT_ID, self._seq),
            airframe=self.airframe,
            time=self._clock(),
            sensor_position=sensor,
            heading_deg=heading,
            pitch_deg=None if attitude is None else _clamp(math.degrees(attitude.pitch_rad), 90),
            roll_deg=None if attitude is None else _clamp(math.degrees(attitude.roll_rad), 180),
            airspeed_mps=state.field("airspeed_mps"),
            groundspeed_mps=state.field("groundspeed_mps"),
            alt_agl_m=alt_agl,
            hfov_deg=hfov,
            vfov_deg=vfov,
            **fields,
        )

    def _frame_centre(
        self,
        fields: dict[str, Any],
        sensor: Position,
        pointing: tuple[float, float, float] | None,
        home: float | None,
    ) -> None:
        cam = self._camera
        if cam is not None:
            lat, lon = _degrees_e7(int(cam.lat_image)), _degrees_e7(int(cam.lon_image))
            if lat is not None and lon is not None and -90 <= lat <= 90 and -180 <= lon <= 180:
                alt = (
                    None
                    if int(cam.alt_image) == _INT32_MAX
                    else plausible_alt(cam.alt_image / 1000.0)
                )
                fields["frame_centre"] = Position(lat_deg=lat, lon_deg=lon, alt_msl_m=alt)
                fields["frame_centre_source"] = "camera"
                if alt is not None and sensor.alt_msl_m is not None:
                    ground_m, _ = distance_bearing(sensor.lat_deg, sensor.lon_deg, lat, lon)
                    fields["slant_range_m"] = math.hypot(ground_m, sensor.alt_msl_m - alt)
                return
        if pointing is None or sensor.alt_msl_m is None:
            return
        azimuth, elevation, _ = pointing
        where = (sensor.lat_deg, sensor.lon_deg, sensor.alt_msl_m, azimuth, elevation)
        if self._terrain is not None:
            hit = ground_intersection(*where, self._ground, fallback_ground_msl_m=home)
        else:
            hit = None if home is None else flat_intersection(*where, home)
        if hit is None:
            # Known ground and a pointing that misses it: the axis is off the earth.
            fields["is_off_earth"] = home is not None or self._terrain is not None
            return
        fields["frame_centre"] = Position(
            lat_deg=hit.lat_deg, lon_deg=hit.lon_deg, alt_msl_m=hit.elevation_msl_m
        )
        fields["frame_centre_source"] = "computed"
        fields["slant_range_m"] = hit.slant_range_m


def _wrap(degrees: float) -> float:
    """``degrees`` in [0, 360): ``%`` alone gives 360.0 for a tiny negative number."""
    wrapped = degrees % 360.0
    return 0.0 if wrapped >= 360.0 else wrapped


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))
