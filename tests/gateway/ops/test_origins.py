"""Other nodes' events on /status: per node and per airframe, bounded whatever they send."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from gateway.events import Detection, Event, Position, Sensor, Telemetry
from gateway.ops.origins import AIRFRAME_CHARS, RemoteOrigins

T0 = datetime(2026, 11, 27, 10, 0, tzinfo=UTC)


class Clock:
    def __init__(self) -> None:
        self.now = T0

    def __call__(self) -> datetime:
        return self.now


def telemetry(airframe: str, node: str | None) -> Telemetry:
    return Telemetry(event_id=f"t-{airframe}", airframe=airframe, time=T0, origin_node=node)


def detection(airframe: str, node: str | None, n: int = 1) -> Detection:
    return Detection(
        event_id=f"{airframe}-det-{n}",
        airframe=airframe,
        time=T0,
        sensor=Sensor.EO,
        object_class="tank",
        confidence=0.9,
        position=Position(lat_deg=58.0, lon_deg=15.0),
        sigma_h_m=5.0,
        origin_node=node,
    )


def test_each_remote_node_with_its_events_last_heard_and_airframes() -> None:
    clock = Clock()
    origins = RemoteOrigins(clock=clock)
    bus: list[Event] = []
    publish = origins.wrap(lambda e: bus.append(e) is None)
    publish(telemetry("B-1", "b"))
    publish(detection("B-1", "b"))
    publish(detection("OWN", None))  # this node's own: passed on, not counted
    clock.now = T0 + timedelta(seconds=5)
    publish(telemetry("C-1", "c"))
    clock.now = T0 + timedelta(seconds=7)
    status = origins.status()
    assert len(bus) == 4
    assert status["nodes"] == {
        "b": {
            "events": 2,
            "by_kind": {"telemetry": 1, "detection": 1},
            "last_heard": T0.isoformat(),
            "last_heard_age_s": 7.0,
            "airframes": 1,
        },
        "c": {
            "events": 1,
            "by_kind": {"telemetry": 1},
            "last_heard": (T0 + timedelta(seconds=5)).isoformat(),
            "last_heard_age_s": 2.0,
            "airframes": 1,
        },
    }
    assert status["airframes"] == {
        "C-1": {"origin_node": "c", "last_heard": (T0 + timedelta(seconds=5)).isoformat()},
        "B-1": {"origin_node": "b", "last_heard": T0.isoformat()},
    }
    assert list(status["airframes"]) == ["C-1", "B-1"]  # newest first


def test_an_event_the_bus_refused_is_not_counted() -> None:
    origins = RemoteOrigins()
    assert origins.wrap(lambda e: False)(detection("B-1", "b")) is False
    assert origins.status()["nodes"] == {}


def test_an_airframe_heard_from_a_second_node_moves_to_it() -> None:
    origins = RemoteOrigins()
    origins.record(telemetry("X", "b"))
    origins.record(telemetry("X", "c"))
    status = origins.status()
    assert status["airframes"]["X"]["origin_node"] == "c"
    assert status["nodes"]["b"]["airframes"] == 0
    assert status["nodes"]["c"]["airframes"] == 1


def test_an_own_airframe_is_never_listed_as_another_nodes() -> None:
    # A detection of this node's own airframe relayed (or forged) on node b's subjects is
    # counted under b, but the airframe stays this node's.
    origins = RemoteOrigins(own=frozenset({"A-001"}))
    origins.record(detection("A-001", "b"))
    status = origins.status()
    assert status["nodes"]["b"]["events"] == 1
    assert status["nodes"]["b"]["airframes"] == 0
    assert status["airframes"] == {}


def test_nodes_and_airframes_are_bounded() -> None:
    origins = RemoteOrigins(max_nodes=3, max_airframes=50)
    for n in range(10):
        for k in range(40):
            origins.record(detection(f"{n}-{k}" + "x" * 300, f"n{n}", k))
    status = origins.status()
    assert sorted(status["nodes"]) == ["n0", "n1", "n2"]
    assert status["nodes_dropped"] == 7 * 40
    assert len(status["airframes"]) == 50
    assert status["airframes_forgotten"] == 3 * 40 - 50
    assert sum(node["airframes"] for node in status["nodes"].values()) == 50
    assert max(len(airframe) for airframe in status["airframes"]) == AIRFRAME_CHARS
