"""``events.checked``: the instance the validating constructor builds, without validation."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
from pydantic import ValidationError

from gateway.events import (
    Attitude,
    Detection,
    EventKind,
    Position,
    Sensor,
    Telemetry,
    checked,
    event_adapter,
)

T0 = datetime(2026, 11, 27, 8, 0, tzinfo=UTC)


def test_the_same_event_as_validation_builds_field_order_and_json_included() -> None:
    position = {"lat_deg": 65.8, "lon_deg": 21.7, "alt_msl_m": 60.0}
    values = {
        "event_id": "det-1",
        "airframe": "F26E-001",
        "time": T0,
        "sensor": Sensor.IR,
        "object_class": "tank",
        "confidence": 0.91,
        "sigma_h_m": 8.0,
    }
    ours = checked(Detection, **values, position=checked(Position, **position))
    theirs = Detection(**values, position=Position(**position))
    assert ours == theirs
    assert ours.model_dump_json() == theirs.model_dump_json()
    assert ours.model_fields_set == theirs.model_fields_set
    assert ours.kind is EventKind.DETECTION
    assert event_adapter.validate_json(ours.model_dump_json()) == theirs
    assert hash(ours) == hash(theirs)


def test_defaults_fill_what_is_not_given_and_instances_stay_frozen() -> None:
    attitude = checked(Attitude, roll_rad=0.1, pitch_rad=0.0, yaw_rad=1.0)
    telemetry = checked(Telemetry, event_id="t-1", airframe="F26E-001", time=T0, attitude=attitude)
    assert telemetry == Telemetry(event_id="t-1", airframe="F26E-001", time=T0, attitude=attitude)
    assert telemetry.position is None
    assert telemetry.kind is EventKind.TELEMETRY
    with pytest.raises(ValidationError, match="frozen"):
        telemetry.airframe = "other"  # type: ignore[misc]
