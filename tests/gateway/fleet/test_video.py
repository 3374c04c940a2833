"""Camera and gimbal MAVLink to VideoFrameMetadata (fleet/video.py), through ingest."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.config import AirframeConfig, LinkConfig
from gateway.domain.geodesy import distance_bearing
from gateway.events import Event, VideoFrameMetadata
from gateway.fleet.ingest import Ingest, LinkIntake
from gateway.fleet.normalise import AirframeState
from gateway.fleet.video import CameraView
from gateway.ops.instruments import Instruments
from gateway.sim.airframe import SimProfile, SimulatedAirframe
from gateway.testing import fuzz_examples
from sinks.klv.imapb import Special
from sinks.klv.st0601 import decode
from sinks.klv.uas import frame_packet

stanag = pytest.importorskip("stanag4609.st0601")
T0 = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)
PROFILE = SimProfile(camera_hz=5, alt_msl_m=600, home_alt_msl_m=150, radius_m=700)
INT32_MAX = 0x7FFFFFFF
NAN4 = [math.nan] * 4


def make_ingest() -> tuple[Ingest, list[Event]]:
    events: list[Event] = []
    link = LinkConfig(uri="udp://127.0.0.1:1", name="l", security="unsecured")
    ingest = Ingest([AirframeConfig(id="AF-1", sysid=1, links=(link,))], events.append,
                    Instruments(), lambda: T0)  # fmt: skip
    ingest.register_link(LinkIntake("l", "unsecured", is_stream=False))
    return ingest, events


def frames(ingest: Ingest, sim: SimulatedAirframe, until_s: float) -> None:
    t = 0.0
    while t <= until_s:
        for frame in sim.frames_at(t):
            ingest.on_data("l", ("127.0.0.1", 1), frame)
        t += 0.1
    ingest.flush()


def video(events: list[Event]) -> list[VideoFrameMetadata]:
    return [e for e in events if isinstance(e, VideoFrameMetadata)]


def test_the_simulated_camera_reaches_the_bus_as_video_frame_metadata() -> None:
    ingest, events = make_ingest()
    frames(ingest, SimulatedAirframe(1, PROFILE), 2.0)
    got = video(events)
    # The very first gimbal report comes before any camera report: that one is computed.
    assert [e.frame_centre_source for e in got[:1]] == ["computed"]
    assert len(got) >= 1 + 10  # then one per camera report: 5 Hz for 2 s
    for event in got[1:]:
        assert event.frame_centre_source == "camera"
        assert event.frame_centre is not None
        centre = (event.frame_centre.lat_deg, event.frame_centre.lon_deg)
        assert centre == pytest.approx((PROFILE.centre_lat_deg, PROFILE.centre_lon_deg))
        assert event.slant_range_m == pytest.approx(math.hypot(700, 450), rel=1e-3)
        assert event.hfov_deg == pytest.approx(12.5)
        assert event.sensor_azimuth_deg == pytest.approx(90.0, abs=5.0)  # to the right
        assert event.target_width_m == pytest.approx(
            2 * 832.0 * math.tan(math.radians(6.25)), rel=0.01
        )


class Camera:
    """A CameraView fed by a simulated airframe's own messages, with some of them altered."""

    def __init__(self) -> None:
        self.sim = SimulatedAirframe(1, PROFILE)
        self.state = AirframeState("AF-1", lambda: T0)
        self.view = CameraView("AF-1", self.state, lambda: T0)
        self.mav = mav.MAVLink(None, srcSystem=1, srcComponent=100)

    def telemetry(self, t_s: float) -> None:
        for msg in self.sim.messages_at(t_s):
            name = msg.get_type()
            self.state.update(name, msg)
            if name == "GIMBAL_DEVICE_ATTITUDE_STATUS":
                self.view.gimbal_attitude(msg)

    def blind_camera(self) -> VideoFrameMetadata | None:
        """A camera that knows its field of view but neither its attitude nor the centre."""
        msg = self.mav.camera_fov_status_encode(0, INT32_MAX, INT32_MAX, INT32_MAX, INT32_MAX,
                                                INT32_MAX, INT32_MAX, NAN4, 12.5, 7.0)  # fmt: skip
        return self.view.camera_fov(msg)


def test_without_the_camera_centre_it_is_computed_from_gimbal_and_attitude() -> None:
    camera = Camera()
    camera.telemetry(0.0)
    event = camera.blind_camera()
    assert event is not None
    assert event.frame_centre_source == "computed"
    assert event.frame_centre is not None
    miss_m, _ = distance_bearing(event.frame_centre.lat_deg, event.frame_centre.lon_deg,
                                 PROFILE.centre_lat_deg, PROFILE.centre_lon_deg)  # fmt: skip
    assert miss_m < 2.0  # flat ground at home altitude, as the simulator's gimbal assumes
    assert event.slant_range_m == pytest.approx(math.hypot(700, 450), rel=1e-3)


def test_a_gimbal_without_a_camera_is_enough() -> None:
    camera = Camera()
    camera.telemetry(0.0)
    gimbal = [m for m in camera.sim.messages_at(0.2) if m.get_type().startswith("GIMBAL")]
    event = camera.view.gimbal_attitude(gimbal[0])
    assert event is not None
    assert event.frame_centre_source == "computed"
    assert event.hfov_deg is None


def test_looking_above_the_horizon_is_off_earth_in_klv() -> None:
    camera = Camera()
    camera.telemetry(0.0)
    up = [math.cos(0.2), 0.0, math.sin(0.2), 0.0]  # pitched 23° up
    msg = camera.mav.gimbal_device_attitude_status_encode(0, 0, 0, 32, up, 0, 0, 0, 0)
    event = camera.view.gimbal_attitude(msg)
    assert event is not None
    assert event.is_off_earth
    assert event.frame_centre is None
    values = decode(frame_packet(event))
    assert values[23] is values[24] is Special.ERROR


def test_no_position_no_event() -> None:
    camera = Camera()
    assert camera.blind_camera() is None


int32 = st.integers(-(2**31), 2**31 - 1)
anything = st.floats(allow_nan=True, allow_infinity=True, width=32)


@settings(max_examples=fuzz_examples(200))
@given(st.lists(int32, min_size=6, max_size=6), st.lists(anything, min_size=6, max_size=6),
       st.integers(0, 0xFFFF), st.booleans())  # fmt: skip
def test_hostile_camera_and_gimbal_values_never_raise(
    ints: list[int], floats: list[float], flags: int, with_telemetry: bool
) -> None:
    camera = Camera()
    if with_telemetry:
        camera.telemetry(0.0)
    msg: Any = camera.mav.camera_fov_status_encode(0, *ints, floats[:4], floats[4], floats[5])
    gimbal: Any = camera.mav.gimbal_device_attitude_status_encode(
        0, 0, 0, flags, floats[:4], 0, 0, 0, 0
    )
    for event in (camera.view.gimbal_attitude(gimbal), camera.view.camera_fov(msg)):
        if event is not None:
            packet = frame_packet(event)
            decode(packet)  # and every event makes a valid packet, for us
            stanag.decode_uas_local_set(packet)  # and for a strict independent decoder
