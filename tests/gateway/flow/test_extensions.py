"""The extension point: declared types, the envelope's bounds, the gate and the bus."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, ClassVar

import pytest
from pydantic import BaseModel, Field, ValidationError

from gateway.config import RouteConfig
from gateway.errors import ConfigError
from gateway.events import (
    EXTENSION_DATA_MAX_BYTES,
    EXTENSION_DATA_MAX_DEPTH,
    Event,
    EventKind,
    Extension,
    declared_extensions,
    event_adapter,
)
from gateway.flow.bus import Bus
from gateway.flow.processors import ProcessorRunner
from gateway.ops.instruments import Instruments

T0 = datetime(2026, 11, 23, 12, tzinfo=UTC)


class Weather(BaseModel):
    wind_mps: float = Field(ge=0)


class Feed:
    """A processor declaring one type; what it publishes is driven by the test."""

    config_model = BaseModel
    extension_events: ClassVar[dict[str, type[BaseModel]]] = {"acme.weather": Weather}
    kinds = frozenset({EventKind.DETECTION})

    def __init__(self, name: str = "feed") -> None:
        self.name = name

    async def run(self, *args: Any, **kwargs: Any) -> None:
        raise AssertionError("not run here")


class Sink:
    """A sink runner stand-in that keeps what it is offered."""

    def __init__(self, name: str, kinds: frozenset[EventKind]) -> None:
        self.name = name
        self.description = f"sink {name!r} (test)"
        self.kinds = kinds
        self.got: list[Event] = []

    def offer_slot(self, event: Event, ingest_mono: float, slot: str | None) -> None:
        self.got.append(event)

    def offer_spooled(self, event: Event, ingest_mono: float, seq: int) -> None:
        self.got.append(event)

    def refused(self, event: Event) -> None:
        raise AssertionError(f"refused {event.event_id}")


def weather(data: dict[str, Any], type_name: str = "acme.weather", **more: Any) -> Extension:
    return Extension(event_id="w1", type=type_name, time=T0, data=data, **more)


@pytest.mark.parametrize("name", ["acme.weather", "acme.radar.sweep", "a1.b_2"])
def test_namespaced_type_names_are_taken(name: str) -> None:
    assert weather({}, name).type == name


@pytest.mark.parametrize(
    "name", ["weather", "Acme.weather", "acme..weather", ".acme", "acme.", "1acme.x", "a.b-c",
             "acme." + "x" * 70, "acme.wéather"],
)  # fmt: skip
def test_other_type_names_are_refused(name: str) -> None:
    with pytest.raises(ValidationError, match="type"):
        weather({}, name)


def test_data_is_bounded_in_size_and_depth() -> None:
    with pytest.raises(ValidationError, match="bytes as JSON"):
        weather({"blob": "x" * EXTENSION_DATA_MAX_BYTES})
    deep: dict[str, Any] = {}
    inner = deep
    for _ in range(EXTENSION_DATA_MAX_DEPTH):
        inner["a"] = {}
        inner = inner["a"]
    with pytest.raises(ValidationError, match="levels deep"):
        weather(deep)
    with pytest.raises(ValidationError):
        event_adapter.validate_json(
            '{"kind": "extension", "event_id": "x", "type": "a.b", "time": "2026-11-23T12:00:00Z",'
            ' "data": [1, 2]}'
        )  # an array is not an object
    ok = weather({"list": [1, {"b": None}], "n": 1.5})
    assert event_adapter.validate_json(ok.model_dump_json()) == ok


def test_declarations_are_read_and_checked() -> None:
    assert declared_extensions(Feed) == {"acme.weather": Weather}
    assert declared_extensions(object()) == {}

    class NotAMapping:
        extension_events = ("acme.weather",)

    class BadName:
        extension_events: ClassVar[dict[str, type]] = {"Weather": Weather}

    class NotAModel:
        extension_events: ClassVar[dict[str, type]] = {"acme.weather": dict}

    for bad, message in (
        (NotAMapping, "must map type names"),
        (BadName, "'Weather' is not a type name"),
        (NotAModel, "must be a pydantic model"),
    ):
        with pytest.raises(ValueError, match=message):
            declared_extensions(bad)


def test_the_runner_refuses_undeclared_and_invalid_counting_them_under_the_processor() -> None:
    inst = Instruments()
    passed: list[Event] = []

    def publish(event: Event) -> bool:
        passed.append(event)
        return True

    runner = ProcessorRunner("wx", "feed", Feed("wx"), inst, publish, queue_max=4)
    runner.close()  # never run: only its publish is used
    assert runner.publish(weather({"wind_mps": 3.0})) is True
    assert runner.publish(weather({"wind_mps": 3.0}, "acme.other")) is False
    assert runner.publish(weather({"wind_mps": -1.0})) is False
    assert runner.publish(weather({"wind_mps": 1.0}, publisher="forged")) is True
    assert [e.publisher for e in passed if isinstance(e, Extension)] == ["wx", "wx"]
    refused = inst.extension_refused
    assert refused.labels("wx", "undeclared").value == 1
    assert refused.labels("wx", "invalid").value == 1
    assert runner.status()["events_out"] == 2


def test_the_bus_takes_an_extension_only_from_its_declaring_processor() -> None:
    inst = Instruments()
    archive = Sink("archive", frozenset(EventKind))
    cot = Sink("cot", frozenset({EventKind.TRACK, EventKind.DETECTION}))
    runners = {"archive": archive, "cot": cot}
    bus: Bus
    runner = ProcessorRunner("wx", "feed", Feed("wx"), inst, lambda e: bus.publish(e), queue_max=4)
    runner.close()  # never run: only its publish is used
    bus = Bus([RouteConfig(sinks=("archive", "cot"))], runners, inst, processors=[runner])
    assert runner.publish(weather({"wind_mps": 2.0})) is True
    # A source (or anything else) publishing straight onto the bus is refused and counted.
    assert bus.publish(weather({"wind_mps": 2.0})) is False
    assert bus.publish(weather({"wind_mps": 2.0}, publisher="other")) is False
    assert [e.kind for e in archive.got] == [EventKind.EXTENSION]
    assert cot.got == []  # a sink that does not declare the kind never sees it
    assert bus.publish(weather({"wind_mps": 2.0}, "acme.other", publisher="wx")) is False
    assert inst.extension_refused.labels("unknown", "undeclared").value == 2
    assert inst.extension_refused.labels("wx", "undeclared").value == 1


def test_a_route_naming_extension_for_a_sink_that_cannot_take_it_is_a_config_error() -> None:
    cot = Sink("cot", frozenset({EventKind.TRACK}))
    with pytest.raises(ConfigError, match="does not accept 'extension'"):
        Bus(
            [RouteConfig(sinks=("cot",), kinds=(EventKind.EXTENSION,))], {"cot": cot}, Instruments()
        )


class Loose(BaseModel):
    """A declared model that takes anything (the envelope's own limits must still hold)."""

    model_config = {"extra": "allow"}


class LooseFeed(Feed):
    extension_events: ClassVar[dict[str, type[BaseModel]]] = {"acme.loose": Loose}


@pytest.mark.parametrize(
    "data",
    [
        {"pad": "x" * (EXTENSION_DATA_MAX_BYTES + 100)},  # past the size limit
        {"big": 10**5000},  # a number JSON readers cannot hold
        {"deep": [[[[[[[[[[[[]]]]]]]]]]]]},  # past the depth limit
    ],
)
def test_an_extension_built_past_its_own_checks_is_refused_before_the_bus(
    data: dict[str, Any],
) -> None:
    """``model_construct`` skips the envelope's checks: the runner's gate makes the whole
    event's JSON round trip, as the spool will, and refuses what does not come back."""
    inst = Instruments()
    passed: list[Event] = []
    runner = ProcessorRunner("wx", "feed", LooseFeed("wx"), inst, passed.append, queue_max=4)
    runner.close()
    forged = Extension.model_construct(
        event_id="e-1", type="acme.loose", time=T0, data=data, publisher="", airframe=None,
        late_by_s=None, kind=EventKind.EXTENSION,
    )  # fmt: skip
    assert runner.publish(forged) is False
    assert passed == []
    assert inst.extension_refused.labels("wx", "invalid").value == 1


def test_a_source_cannot_publish_an_extension_even_naming_a_processor() -> None:
    from gateway.c2.sourcepublish import SourcePublish

    passed: list[Event] = []
    publish = SourcePublish("cot", frozenset(), frozenset(), lambda e: passed.append(e) or True)
    assert publish(weather({"wind_mps": 1.0}, publisher="wx")) is False
    assert passed == []
    assert publish.refused["extension"] == 1


def test_a_plugin_status_that_raises_is_reported_not_raised() -> None:
    from gateway.ops.pluginstatus import read_status

    def broken() -> dict[str, Any]:
        raise RuntimeError("boom")

    assert read_status(broken, "source x") == {"status_error": "RuntimeError: boom"}
    assert read_status(lambda: {"a": 1}, "source y") == {"a": 1}
    assert read_status(lambda: 3, "source z") == {
        "status_error": "status() returned int, not a mapping"
    }
