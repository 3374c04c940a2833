"""Simulator scenarios: what flies, what is seen and who reports, as a validated YAML file.

A scenario names airframes (orbiting as ``SimulatedAirframe`` does, each with its sensors),
hostile targets moving along waypoint paths (a column is several vehicles spaced along one
road), friendly units reporting their positions by CoT, and counter-UAS batteries. The
simulator ignores ``batteries``: they are there so the demo can configure the gateway's
counter-UAS cue (battery position and effectors) from the same file.

Files are read with the config file's bounded loader (``gateway.configfile``), so a bad
scenario is one ``ConfigError`` naming the file, the line and the key path of every problem.
``gateway.sim.schedule`` turns a ``Scenario`` into timed detections and reports.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from gateway.configfile import Loc, load_model_text, read_bounded_text
from gateway.errors import ConfigError, ConfigIssue
from gateway.fleet.dialect import CLASS_NAMES, SENSOR_NAMES
from gateway.sim.airframe import SimProfile
from gateway.sim.autopilot import AutopilotName

__all__ = [
    "CLASS_IDS",
    "SENSOR_IDS",
    "SHIPPED_DIR",
    "Airframe",
    "Battery",
    "BlueForceUnit",
    "ClassName",
    "Column",
    "Orbit",
    "Scenario",
    "SensorName",
    "SensorSpec",
    "Target",
    "Waypoint",
    "load_scenario",
    "load_scenario_text",
    "shipped_scenarios",
]

ClassName = Literal["tank", "armour", "infantry_platoon", "uav", "loitering_munition"]
SensorName = Literal["eo", "ir", "rf"]
#: Class name → FISCHER_DETECTION class_id.
CLASS_IDS: dict[str, int] = {name: number for number, name in CLASS_NAMES.items()}
#: Sensor name → FISCHER_SENSOR value.
SENSOR_IDS: dict[str, int] = {name: number for number, name in SENSOR_NAMES.items()}

_MODEL = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)
_ID = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_Lat = Field(ge=-89.0, le=89.0, description="Latitude, degrees (WGS 84).")
_Lon = Field(ge=-180.0, le=180.0, description="Longitude, degrees (WGS 84).")


class Orbit(BaseModel):
    """A clockwise circle flown at constant speed and altitude, as ``SimProfile`` flies it."""

    model_config = _MODEL

    centre_lat_deg: float = _Lat
    centre_lon_deg: float = _Lon
    radius_m: float = Field(gt=0, le=50_000)
    alt_msl_m: float = Field(ge=-500, le=10_000)
    speed_mps: float = Field(gt=0, le=150)
    phase_deg: float = Field(default=0.0, description="Bearing from the centre at time 0.")


class SensorSpec(BaseModel):
    """One sensor of an airframe: what it reports, how far it sees and how well.

    ``confidence`` is one value for every class or a value per class (a class missing from
    the mapping is not reported by this sensor). ``sigma_h_m`` is the 1-sigma horizontal
    error per axis (north and east), both sent in the detection and applied as noise.
    """

    model_config = _MODEL

    sensor: SensorName
    range_m: float = Field(gt=0, le=100_000)
    confidence: float | dict[ClassName, float]
    sigma_h_m: float = Field(ge=0, le=5_000)
    rate_hz: float = Field(gt=0, le=50)
    classes: tuple[ClassName, ...] | None = Field(
        default=None, description="Report only these classes (all when absent)."
    )

    @model_validator(mode="after")
    def _check_confidence(self) -> SensorSpec:
        values = (
            self.confidence.values() if isinstance(self.confidence, dict) else [self.confidence]
        )
        if any(not 0.0 <= value <= 1.0 for value in values):
            raise ValueError("confidence: expected values in 0..1")
        return self

    def confidence_for(self, object_class: str) -> float | None:
        """The confidence reported for ``object_class``; None if this sensor does not report it."""
        if self.classes is not None and object_class not in self.classes:
            return None
        if isinstance(self.confidence, dict):
            by_class: dict[str, float] = {str(k): v for k, v in self.confidence.items()}
            return by_class.get(object_class)
        return self.confidence


class Airframe(BaseModel):
    """A simulated Fischer 26E: its id (as in the gateway's config), sysid, orbit, sensors,
    and the autopilot it plays (PX4 or ArduPilot: its HEARTBEAT, modes and answers)."""

    model_config = _MODEL

    id: str = Field(pattern=_ID)
    sysid: int = Field(ge=1, le=255)
    orbit: Orbit
    sensors: tuple[SensorSpec, ...] = ()
    camera_hz: float = Field(
        default=0.0, ge=0.0, le=60.0, description="CAMERA_FOV_STATUS and gimbal reports a second"
    )
    autopilot: AutopilotName = "ardupilot"

    def profile(self) -> SimProfile:
        """The flight ``SimulatedAirframe`` flies (its own detections off)."""
        o = self.orbit
        return SimProfile(
            centre_lat_deg=o.centre_lat_deg,
            centre_lon_deg=o.centre_lon_deg,
            radius_m=o.radius_m,
            alt_msl_m=o.alt_msl_m,
            speed_mps=o.speed_mps,
            home_alt_msl_m=min(o.alt_msl_m, SimProfile.home_alt_msl_m),
            camera_hz=self.camera_hz,
        )


class Waypoint(BaseModel):
    """A point of a path."""

    model_config = _MODEL

    lat_deg: float = _Lat
    lon_deg: float = _Lon
    alt_msl_m: float = Field(ge=-500, le=10_000)


class Column(BaseModel):
    """``count`` vehicles one behind the other along the path, ``spacing_m`` apart."""

    model_config = _MODEL

    count: int = Field(ge=2, le=64)
    spacing_m: float = Field(gt=0, le=5_000)


class Target(BaseModel):
    """A hostile object moving along ``path`` at ``speed_mps`` from ``start_s``.

    It appears at the first waypoint at ``start_s``. At the last one it stays (``hold``: a
    vehicle that stopped) or is gone (``vanish``: a munition that struck). With ``column``,
    vehicle ``i`` (ids ``ID-1`` .. ``ID-n``, 1 leading) is ``(i - 1) × spacing_m`` behind the
    lead and appears once that far along the path.
    """

    model_config = _MODEL

    id: str = Field(pattern=_ID)
    object_class: ClassName = Field(alias="class")
    subtype: str = Field(default="", max_length=16, pattern=r"^[\x20-\x7e]*$")
    path: tuple[Waypoint, ...] = Field(min_length=1)
    speed_mps: float = Field(default=0.0, ge=0, le=1_000)
    start_s: float = Field(default=0.0, ge=0)
    at_end: Literal["hold", "vanish"] = "hold"
    column: Column | None = None

    @model_validator(mode="after")
    def _check_motion(self) -> Target:
        if len(self.path) > 1 and self.speed_mps == 0:
            raise ValueError("speed_mps: a path of several waypoints needs a speed > 0")
        return self


class BlueForceUnit(BaseModel):
    """A friendly unit reporting its position by CoT every ``report_interval_s``.

    Give ``position`` (stationary) or ``path`` with ``speed_mps`` (moving from time 0 and
    stopping at the last waypoint), not both.
    """

    model_config = _MODEL

    uid: str = Field(min_length=1, max_length=64, pattern=r"^[\x21-\x7e]+$")
    callsign: str = Field(min_length=1, max_length=64)
    type: str = Field(default="a-f-G-U-C-I", pattern=r"^a-f-[A-Za-z0-9-]*$")
    position: Waypoint | None = None
    path: tuple[Waypoint, ...] | None = Field(default=None, min_length=2)
    speed_mps: float = Field(default=0.0, ge=0, le=100)
    report_interval_s: float = Field(default=10.0, gt=0, le=3600)

    @model_validator(mode="after")
    def _check_where(self) -> BlueForceUnit:
        if (self.position is None) == (self.path is None):
            raise ValueError("expected either position or path (with speed_mps), not both")
        if self.path is not None and self.speed_mps == 0:
            raise ValueError("speed_mps: a path needs a speed > 0")
        return self

    def waypoints(self) -> tuple[Waypoint, ...]:
        """The unit's path; a stationary unit's is its one position."""
        if self.path is not None:
            return self.path
        assert self.position is not None  # noqa: S101 - checked by _check_where
        return (self.position,)


class Battery(BaseModel):
    """A counter-UAS battery (GUTE II). The simulator ignores it; the demo configures the
    gateway's counter-UAS cue from it."""

    model_config = _MODEL

    id: str = Field(pattern=_ID)
    lat_deg: float = _Lat
    lon_deg: float = _Lon
    alt_msl_m: float = Field(ge=-500, le=10_000)
    effectors: tuple[str, ...] = Field(min_length=1)


class Scenario(BaseModel):
    """A whole scenario file."""

    model_config = ConfigDict(
        frozen=True, extra="forbid", allow_inf_nan=False, populate_by_name=True
    )

    name: str = Field(min_length=1, max_length=64)
    description: str = ""
    duration_s: float = Field(gt=0, le=86_400)
    seed: int = Field(default=0, ge=0, description="Seeds the position noise.")
    airframes: tuple[Airframe, ...] = Field(min_length=1)
    targets: tuple[Target, ...] = ()
    blue_forces: tuple[BlueForceUnit, ...] = ()
    batteries: tuple[Battery, ...] = ()


def _duplicates(data: dict[str, Any], section: str, key: str) -> Iterator[tuple[Loc, str]]:
    items = data.get(section)
    if not isinstance(items, list):
        return
    values = [item.get(key) if isinstance(item, dict) else None for item in items]
    counts = Counter(v for v in values if v is not None)
    first: dict[object, int] = {}
    for i, value in enumerate(values):
        if value is None or counts[value] < 2:
            continue
        if value in first:
            yield (section, i, key), f"duplicate {key} {value!r} (also {section}[{first[value]}])"
        else:
            first[value] = i


def _checks(data: dict[str, Any]) -> Iterator[tuple[Loc, str]]:
    yield from _duplicates(data, "airframes", "id")
    yield from _duplicates(data, "airframes", "sysid")
    yield from _duplicates(data, "targets", "id")
    yield from _duplicates(data, "blue_forces", "uid")
    yield from _duplicates(data, "batteries", "id")


def load_scenario_text(text: str, source: str = "<scenario>") -> Scenario:
    """Validate scenario YAML ``text``; ``ConfigError`` naming ``source``, line and key."""
    return load_model_text(text, source, Scenario, checks=_checks)


#: The shipped scenarios. Found from this file: under pytest ``gateway`` can resolve as a
#: namespace package together with ``tests/gateway``.
SHIPPED_DIR = Path(__file__).resolve().parents[1] / "data" / "scenarios"


def shipped_scenarios() -> list[str]:
    """The names of the scenarios shipped with the package (``brigade``, ...), sorted."""
    return sorted(
        entry.name.removesuffix(".yaml")
        for entry in SHIPPED_DIR.iterdir()
        if entry.name.endswith(".yaml")
    )


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a scenario file, or a shipped scenario by name (``brigade`` or ``brigade.yaml``).

    A path that exists wins over a shipped name. Raises ``ConfigError`` naming the file, line
    and key of every problem, or the shipped names when neither is found.
    """
    path = Path(name_or_path)
    if path.exists():
        return load_scenario_text(read_bounded_text(path), str(path))
    name = str(name_or_path).removesuffix(".yaml")
    if name in shipped_scenarios():
        text = read_bounded_text(SHIPPED_DIR / f"{name}.yaml")
        return load_scenario_text(text, f"{name}.yaml (shipped)")
    known = ", ".join(shipped_scenarios())
    message = f"no such scenario file, nor a shipped scenario (shipped: {known})"
    raise ConfigError([ConfigIssue(str(name_or_path), None, "(file)", message)])
