"""``fleet/normalise.py``: the snapshot built without validation is the validated Telemetry."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.config import AirframeConfig, LinkConfig
from gateway.events import ALT_MAX_M, Attitude, Position, Telemetry, Velocity, plausible_alt
from gateway.fleet.mavlink import MavlinkParser
from gateway.fleet.normalise import AirframeState, Enrichment
from gateway.sim.airframe import SimProfile, SimulatedAirframe

T0 = datetime(2026, 11, 27, 8, 0, tzinfo=UTC)


def test_snapshots_equal_what_validation_builds_from_their_values() -> None:
    config = AirframeConfig(
        id="F26E-001",
        sysid=1,
        links=(LinkConfig(uri="udp://127.0.0.1:1", name="l", security="unsecured"),),
    )
    state = AirframeState(
        config.id, lambda: T0, Enrichment(config.energy, config.ew_mode, None, 0.5)
    )
    state.set_active_link("l")
    sim = SimulatedAirframe(1, SimProfile(gps_hz=1.0))
    parser = MavlinkParser(fast=True)
    snapshots = []
    for step in range(40):
        for frame in sim.frames_at(step * 0.05):
            for msg in parser.feed(frame, whole=True):
                if state.update(msg.get_type(), msg):
                    snapshots.append(state.snapshot())
    assert len(snapshots) > 40
    assert len({s.event_id for s in snapshots}) == len(snapshots)
    last = snapshots[-1]
    assert last.position is not None
    assert last.attitude is not None
    assert last.endurance_remaining_min is not None
    assert last.ew_mode is not None
    for ours in snapshots:
        theirs = Telemetry(**{name: getattr(ours, name) for name in ours.model_fields_set})
        assert ours == theirs
        assert ours.model_dump_json() == theirs.model_dump_json()
        assert ours.model_fields_set == theirs.model_fields_set


# -- the hand-checked models against pydantic's validation, on generated messages ----------

#: Degrees x 1e7 at the edges of Position's ranges (latitude ±90°, longitude ±180°).
_EDGES = [sign * (edge + d) for sign in (1, -1) for edge in (900_000_000, 1_800_000_000)
          for d in (-1, 0, 1)]  # fmt: skip
_INT32 = st.one_of(
    st.integers(-900_000_000, 900_000_000),  # mostly a latitude's range: built by hand
    st.integers(-(2**31), 2**31 - 1),  # anything the wire carries: out of range, refused
    st.sampled_from([0, *_EDGES]),
    st.integers(880_000_000, 920_000_000).map(lambda v: v * 2),  # around 180°
    st.integers(880_000_000, 920_000_000),  # around 90°
)
_INT16 = st.integers(-(2**15), 2**15 - 1)
_UINT16 = st.integers(0, 2**16 - 1)
_FLOAT32 = st.floats(width=32)  # NaN and the infinities included
_MESSAGE = st.one_of(
    st.tuples(
        st.just("GLOBAL_POSITION_INT"),
        st.tuples(_INT32, _INT32, _INT32, _INT32, _INT16, _INT16, _INT16, _UINT16),
    ),
    st.tuples(st.just("ATTITUDE"), st.tuples(_FLOAT32, _FLOAT32, _FLOAT32)),
    st.tuples(st.just("GPS_RAW_INT"), st.tuples(st.integers(0, 8), _INT32, _INT32)),
)


def _encode(name: str, values: tuple[Any, ...]) -> bytes:
    m = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    if name == "GLOBAL_POSITION_INT":
        lat, lon, alt, rel, vx, vy, vz, hdg = values
        msg = m.global_position_int_encode(0, lat, lon, alt, rel, vx, vy, vz, hdg)
    elif name == "ATTITUDE":
        msg = m.attitude_encode(0, *values, 0.0, 0.0, 0.0)
    else:
        fix, alt, alt_ellipsoid = values
        msg = m.gps_raw_int_encode(
            0, fix, 590_000_000, 180_000_000, alt, 100, 100, 0, 0, 12, alt_ellipsoid, 500
        )
    return bytes(msg.pack(m))


class _Validated:
    """The validating path: GLOBAL_POSITION_INT and ATTITUDE as pydantic validates them."""

    def __init__(self) -> None:
        self.sep: float | None = None
        self.models: dict[str, Any] = {"position": None, "velocity": None, "attitude": None}

    def take(self, msg: Any) -> bool | None:
        """True if merged, False if ignored, None if validation refused it."""
        name = msg.get_type()
        if name == "GPS_RAW_INT":
            if msg.alt_ellipsoid and msg.fix_type >= 3:
                self.sep = (msg.alt_ellipsoid - msg.alt) / 1000.0
            return True
        if name == "ATTITUDE":
            if not all(math.isfinite(v) for v in (msg.roll, msg.pitch, msg.yaw)):
                return False
            self.models["attitude"] = Attitude(
                roll_rad=msg.roll, pitch_rad=msg.pitch, yaw_rad=msg.yaw
            )
            return True
        try:
            if msg.lat == 0 and msg.lon == 0:
                pos = None
            else:
                msl = plausible_alt(msg.alt / 1000.0)
                rel = msg.relative_alt / 1000.0
                pos = Position(
                    lat_deg=msg.lat / 1e7,
                    lon_deg=msg.lon / 1e7,
                    alt_msl_m=msl,
                    alt_hae_m=None
                    if self.sep is None or msl is None
                    else plausible_alt(msl + self.sep),
                    alt_rel_home_m=rel if -ALT_MAX_M <= rel <= ALT_MAX_M else None,
                )
            vel = Velocity(
                north_mps=msg.vx / 100.0, east_mps=msg.vy / 100.0, down_mps=msg.vz / 100.0
            )
        except ValidationError:
            return None
        self.models["position"], self.models["velocity"] = pos, vel
        return True


@settings(max_examples=150, deadline=None)
@given(st.lists(_MESSAGE, min_size=1, max_size=12), st.booleans())
def test_hand_checked_models_equal_validation_on_generated_messages(
    messages: list[tuple[str, tuple[Any, ...]]], fast: bool
) -> None:
    """Built by hand or refused, exactly as pydantic's validating constructors would: on the
    fast decoder's messages and on pymavlink's, in any order, snapshot or not in between."""
    state = AirframeState("F26E-001", lambda: T0)
    parser = MavlinkParser(fast=fast)
    validated = _Validated()
    for n, (name, values) in enumerate(messages):
        (msg,) = parser.feed(_encode(name, values), whole=True)
        expected = validated.take(msg)
        try:
            merged: bool | None = state.update(name, msg)
        except ValidationError:
            merged = None
        assert merged == expected, (name, values)
        if n % 3 == 2 or n == len(messages) - 1:  # merged messages, then a snapshot
            snapshot = state.snapshot()
            for field, theirs in validated.models.items():
                ours = getattr(snapshot, field)
                assert ours == theirs
                assert state.field(field) == theirs
                if theirs is not None:
                    assert type(ours) is type(theirs)
                    assert ours.model_dump_json() == theirs.model_dump_json()
                    assert ours.model_fields_set == theirs.model_fields_set
                    assert ours.model_dump() == theirs.model_dump()
