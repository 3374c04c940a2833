"""The bus: routes, per-kind rate limits, processors by kind."""

from __future__ import annotations

from datetime import UTC, datetime

from gateway.config import RouteConfig
from gateway.events import Detection, Event, EventKind, Position, Sensor, Telemetry
from gateway.flow.bus import Bus
from gateway.ops.instruments import Instruments

T0 = datetime(2026, 11, 23, 12, tzinfo=UTC)


class Taker:
    name = "taker"
    description = "sink 'taker' (test)"
    kinds = frozenset(EventKind)

    def __init__(self) -> None:
        self.got: list[Event] = []

    def offer_slot(self, event: Event, ingest_mono: float, slot: str | None) -> None:
        self.got.append(event)

    def offer_spooled(self, event: Event, ingest_mono: float, seq: int) -> None:
        self.got.append(event)

    def refused(self, event: Event) -> None:
        raise AssertionError(f"refused {event.event_id}")


def telemetry(n: int) -> Telemetry:
    return Telemetry(event_id=f"t{n}", airframe="A", time=T0)


def test_a_routes_rate_limit_thins_telemetry_even_after_a_detection_came_first() -> None:
    taker = Taker()
    bus = Bus([RouteConfig(sinks=("taker",), max_rate_hz=1.0)], {"taker": taker}, Instruments())
    bus.publish(
        Detection(
            event_id="d", airframe="A", time=T0, sensor=Sensor.EO, object_class="tank",
            confidence=0.9, position=Position(lat_deg=1, lon_deg=1), sigma_h_m=5,
        )
    )  # fmt: skip
    for n in range(100):
        bus.publish(telemetry(n))
    kinds = [e.kind for e in taker.got]
    assert kinds.count(EventKind.DETECTION) == 1  # durable: never thinned
    assert kinds.count(EventKind.TELEMETRY) == 1  # 100 in well under a second, at 1 Hz
