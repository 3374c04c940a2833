"""Fan-out of events to subscribers: sink runners by the routes of the config, processors by kind.

``Bus.publish`` is synchronous and never blocks: it hands each event to the subscribers its
routes select (each applies its own queue policy) and to every processor that consumes its
kind. The route decision for a (kind, airframe, class) triple is computed once and cached, so
the hot path is one dict lookup plus one ``offer_slot`` per destination. The bus knows
subscribers only through ``gateway.flow.subscriber.Subscriber``.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import structlog

from gateway.config import RouteConfig
from gateway.errors import ConfigError, ConfigIssue
from gateway.events import LATEST_WINS_KINDS, Detection, Event, EventKind, Track, latest_key
from gateway.flow.subscriber import Subscriber
from gateway.ops.instruments import Instruments

__all__ = ["Bus"]

_MAX_CACHED_ROUTES = 4096

log = structlog.get_logger(__name__)


@dataclass(slots=True)
class _Target:
    runner: Subscriber
    min_interval_s: float | None
    last_sent: dict[str, float]


def _airframes_of(event: Event) -> tuple[str, ...] | None:
    if isinstance(event, Track):
        return event.airframes
    airframe = getattr(event, "airframe", None)
    return None if airframe is None else (airframe,)


def _class_of(event: Event) -> str | None:
    if isinstance(event, Detection | Track):
        return event.object_class
    return None


class Bus:
    """Routes each published event to the runners of the sinks its routes name.

    A route's filters that do not apply to an event's kind (a class filter on telemetry,
    an airframe filter on a blue-force report) do not restrict it.
    """

    def __init__(
        self,
        routes: Iterable[RouteConfig],
        runners: Mapping[str, Subscriber],
        instruments: Instruments,
        *,
        source: str = "<config>",
        processors: Iterable[Subscriber] = (),
    ) -> None:
        self._routes = tuple(routes)
        self._runners = runners
        self._processors = tuple(processors)
        self._by_kind: dict[EventKind, tuple[Subscriber, ...]] = {
            kind: tuple(p for p in self._processors if kind in p.kinds) for kind in EventKind
        }
        self._inst = instruments
        self._cache: dict[tuple[EventKind, tuple[str, ...] | None, str | None], list[_Target]] = {}
        self._targets: dict[tuple[int, str, EventKind], _Target] = {}
        self._event_counters = {kind: instruments.events.labels(kind.value) for kind in EventKind}
        self._check(source)

    def _check(self, source: str) -> None:
        """A route that sends a sink a kind it does not accept is a config error."""
        issues = []
        for i, route in enumerate(self._routes):
            for name in route.sinks:
                runner = self._runners[name]
                for kind in route.kinds or ():
                    if kind not in runner.kinds:
                        issues.append(
                            ConfigIssue(
                                source,
                                None,
                                f"routes[{i}].kinds",
                                f"{runner.description} does not accept "
                                f"{kind.value!r}; it accepts "
                                f"{sorted(k.value for k in runner.kinds)}",
                            )
                        )
        if issues:
            raise ConfigError(issues)

    def _resolve(
        self, kind: EventKind, airframes: tuple[str, ...] | None, cls: str | None
    ) -> list[_Target]:
        targets: list[_Target] = []
        seen: set[str] = set()
        for i, route in enumerate(self._routes):
            if route.kinds is not None and kind not in route.kinds:
                continue
            wanted = route.airframes
            if (
                wanted is not None
                and airframes is not None
                and "*" not in wanted
                and not any(a in wanted for a in airframes)
            ):
                continue
            if route.classes is not None and cls is not None and cls not in route.classes:
                continue
            for name in route.sinks:
                runner = self._runners[name]
                if kind not in runner.kinds or name in seen:
                    continue
                seen.add(name)
                rate = route.max_rate_hz if kind in LATEST_WINS_KINDS else None
                # Per kind: a route's max_rate_hz thins latest-wins kinds only, whichever kind
                # happened to be routed first.
                target = self._targets.get((i, name, kind))
                if target is None:
                    target = _Target(runner, None if rate is None else 1.0 / rate, {})
                    self._targets[(i, name, kind)] = target
                targets.append(target)
        return targets

    def publish(self, event: Event) -> bool:
        """Hand ``event`` to every runner its routes select; never blocks, never raises.

        True once the event is held durably for every sink it goes to (or needs no spool).
        """
        self._event_counters[event.kind].inc()
        consumers = self._by_kind[event.kind]
        if consumers:
            slot = latest_key(event)
            now = time.monotonic()
            for consumer in consumers:
                consumer.offer_slot(event, now, slot)
        key = (event.kind, _airframes_of(event), _class_of(event))
        targets = self._cache.get(key)
        if targets is None:
            targets = self._resolve(*key)
            if len(self._cache) >= _MAX_CACHED_ROUTES:
                # Keys include classes and airframes from the network: bounded, not a leak.
                self._cache.clear()
            self._cache[key] = targets
        if not targets:
            return True
        now = time.monotonic()
        slot = latest_key(event)
        for target in targets:
            interval = target.min_interval_s
            if interval is not None and slot is not None:
                last = target.last_sent.get(slot)
                if last is not None and now - last < interval:
                    self._inst.sink_rate_limited.labels(target.runner.name).inc()
                    continue
                target.last_sent[slot] = now
            target.runner.offer_slot(event, now, slot)
        return True
