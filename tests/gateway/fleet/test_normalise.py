"""``fleet/normalise.py``: the snapshot built without validation is the validated Telemetry."""

from __future__ import annotations

from datetime import UTC, datetime

from gateway.config import AirframeConfig, LinkConfig
from gateway.events import Telemetry
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
