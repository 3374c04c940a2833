"""A ``VideoFrameMetadata`` event as one ST 0601 packet: which tag each field goes to.

The packet carries the precision time stamp, the version (ST 0601.19), the platform (tail
number = the airframe id, designation, heading, pitch, roll, airspeeds), the sensor
(position, true and ellipsoid altitude, fields of view, relative pointing), the slant range,
the target width and the frame centre. A frame centre off the earth is sent as tag 23/24's
"off earth" indicator; pitch and roll beyond ST 0601's legacy ranges (±20°, ±50°) as the
"out of range" indicator in tags 6/7 with the value in the full-range tags 90/91. The AGL
height goes in tag 113 (IMAPB). Fields the event does not know are left out.
"""

from __future__ import annotations

from gateway.events import VideoFrameMetadata
from sinks.klv.imapb import Special
from sinks.klv.st0601 import VERSION, Value, encode

__all__ = ["frame_packet", "frame_values"]

_PITCH_LEGACY, _ROLL_LEGACY = 20.0, 50.0
_TARGET_WIDTH_MAX_M = 10_000.0


def frame_values(
    event: VideoFrameMetadata,
    *,
    mission_id: str | None = None,
    platform_designation: str = "Fischer 26E",
) -> dict[int, Value]:
    """``{tag: value}`` of the ST 0601 packet for ``event`` (see the module docstring)."""
    values: dict[int, Value] = {2: event.time, 4: event.airframe, 10: platform_designation}
    if mission_id:
        values[3] = mission_id
    values[11] = event.image_source
    values[12] = "WGS-84"
    values[65] = VERSION
    sensor = event.sensor_position
    values[13], values[14] = sensor.lat_deg, sensor.lon_deg
    optional: dict[int, float | None] = {
        5: event.heading_deg,
        15: sensor.alt_msl_m,
        16: event.hfov_deg,
        17: event.vfov_deg,
        18: event.sensor_azimuth_deg,
        19: event.sensor_elevation_deg,
        20: event.sensor_roll_deg,
        21: event.slant_range_m,
        75: sensor.alt_hae_m,
        113: event.alt_agl_m,
    }
    values.update({tag: v for tag, v in optional.items() if v is not None})
    if event.pitch_deg is not None:
        values[6] = event.pitch_deg
        if abs(event.pitch_deg) > _PITCH_LEGACY:
            values[90] = event.pitch_deg
    if event.roll_deg is not None:
        values[7] = event.roll_deg
        if abs(event.roll_deg) > _ROLL_LEGACY:
            values[91] = max(-90.0, min(90.0, event.roll_deg))
    for tag, speed in ((8, event.airspeed_mps), (56, event.groundspeed_mps)):
        if speed is not None and 0 <= speed < 255.5:
            values[tag] = round(speed)
    if event.target_width_m is not None and event.target_width_m <= _TARGET_WIDTH_MAX_M:
        values[22] = event.target_width_m
    centre = event.frame_centre
    if centre is not None:
        values[23], values[24] = centre.lat_deg, centre.lon_deg
        if centre.alt_msl_m is not None:
            values[25] = centre.alt_msl_m
    elif event.is_off_earth:
        values[23] = values[24] = Special.ERROR
    return values


def frame_packet(
    event: VideoFrameMetadata,
    *,
    mission_id: str | None = None,
    platform_designation: str = "Fischer 26E",
) -> bytes:
    """The ST 0601 packet for ``event``."""
    return encode(
        frame_values(event, mission_id=mission_id, platform_designation=platform_designation)
    )
