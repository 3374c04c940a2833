"""Fan-out of events to subscribers: sink runners by the routes of the config, processors by kind.

``Bus.publish`` is synchronous and never blocks: it hands each event to the subscribers its
routes select (each applies its own queue policy) and to every processor that consumes its
kind. A durable event bound for sinks is first written to the spool once, for all of them
(``Spool.append``), and only then handed to their runners; ``publish`` returns False when the
spool refused it (full or failing), so a caller that can have it sent again does not
acknowledge it. The route decision for a (kind, airframe, class) triple is computed once and
cached, so the hot path is one dict lookup plus one offer per destination. The bus knows
subscribers only through ``Subscriber`` and ``SpoolingSubscriber``. An ``extension`` event is
taken only from the processor that declares its type (its runner checked the data first,
``gateway.flow.extensions``); any other is refused and counted (``fg_extension_refused_total``).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol, cast

import structlog

from gateway.config import RouteConfig
from gateway.errors import ConfigError, ConfigIssue, SpoolError
from gateway.events import (
    LATEST_WINS_KINDS,
    Detection,
    Event,
    EventKind,
    Extension,
    Track,
    latest_key,
)
from gateway.flow.subscriber import Subscriber
from gateway.ops.instruments import Instruments
from gateway.ops.logsetup import RateLimit
from gateway.spool.store import Spool

__all__ = ["Bus", "SpoolingSubscriber"]

_MAX_CACHED_ROUTES = 4096
_EXTENSION = EventKind.EXTENSION  # a module global: cheaper to read than the enum's member

log = structlog.get_logger(__name__)


class SpoolingSubscriber(Subscriber, Protocol):
    """A subscriber that takes durable events already in the spool (a sink runner)."""

    def offer_spooled(self, event: Event, ingest_mono: float, seq: int) -> None:
        """Take ``event``, held in the spool as ``seq`` for this subscriber."""
        ...

    def refused(self, event: Event) -> None:
        """Count ``event``, which the spool had no room for."""
        ...


@dataclass(slots=True)
class _Target:
    runner: SpoolingSubscriber
    min_interval_s: float | None
    last_sent: dict[str, float]


class _Targets(list[_Target]):
    """The targets of one route decision, and their sink names (what the spool holds it for)."""

    __slots__ = ("names",)

    def __init__(self, targets: list[_Target]) -> None:
        super().__init__(targets)
        self.names = tuple(target.runner.name for target in targets)


def _airframes_of(event: Event) -> tuple[str, ...] | None:
    if isinstance(event, Track):
        return event.airframes
    airframe = getattr(event, "airframe", None)
    return None if airframe is None else (airframe,)


def _extension_types(subscriber: Subscriber) -> frozenset[str]:
    gate = getattr(subscriber, "extensions", None)
    types = getattr(gate, "types", None)
    return types if isinstance(types, frozenset) else frozenset()


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
        runners: Mapping[str, SpoolingSubscriber],
        instruments: Instruments,
        *,
        source: str = "<config>",
        processors: Iterable[Subscriber] = (),
        spool: Spool | None = None,
    ) -> None:
        self._routes = tuple(routes)
        self._spool = spool if spool is not None else Spool()
        for runner in runners.values():
            theirs = getattr(runner, "spool", self._spool)
            if theirs is not self._spool:
                # Sequence numbers of one spool confirmed in another would settle wrong rows.
                raise ValueError(f"{runner.description} has a spool of its own, not the bus's")
        self._runners = runners
        self._processors = tuple(processors)
        self._by_kind: dict[EventKind, tuple[Subscriber, ...]] = {
            kind: tuple(p for p in self._processors if kind in p.kinds) for kind in EventKind
        }
        self._inst = instruments
        self._cache: dict[tuple[EventKind, tuple[str, ...] | None, str | None], _Targets] = {}
        self._targets: dict[tuple[int, str, EventKind], _Target] = {}
        self._event_counters = {kind: instruments.events.labels(kind.value) for kind in EventKind}
        self._publishers = frozenset(p.name for p in self._processors)
        # (publisher, type) of every extension type a processor declares: all the bus takes.
        self._extensions = frozenset(
            (name, type_name)
            for p in self._processors
            for name, types in [(p.name, _extension_types(p))]
            for type_name in types
        )
        self._spool_log = RateLimit(interval_s=10.0)
        self._refused_log = RateLimit(interval_s=10.0)
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
    ) -> _Targets:
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
        return _Targets(targets)

    def publish(self, event: Event) -> bool:
        """Hand ``event`` to every runner its routes select; never blocks, never raises.

        True once the event is held durably for every sink it goes to (or needs no spool).
        A durable event the spool refuses goes to no one, processors included: its sender
        (an airframe that was not acknowledged) sends it again, and it must count once.
        """
        kind = event.kind
        # By kind, not isinstance: cheaper on the hot path, and it catches a subclass too.
        if kind is _EXTENSION and not self._admits(cast("Extension", event)):
            return False
        self._event_counters[kind].inc()
        key = (kind, _airframes_of(event), _class_of(event))
        targets = self._cache.get(key)
        if targets is None:
            targets = self._resolve(*key)
            if len(self._cache) >= _MAX_CACHED_ROUTES:
                # Keys include classes and airframes from the network: bounded, not a leak.
                self._cache.clear()
            self._cache[key] = targets
        now = time.monotonic()
        slot = latest_key(event)
        if slot is None and targets and not self._publish_durable(event, targets, now):
            return False
        for consumer in self._by_kind[event.kind]:
            consumer.offer_slot(event, now, slot)
        if slot is None:
            return True
        for target in targets:
            interval = target.min_interval_s
            if interval is not None:
                last = target.last_sent.get(slot)
                if last is not None and now - last < interval:
                    self._inst.sink_rate_limited.labels(target.runner.name).inc()
                    continue
                target.last_sent[slot] = now
            target.runner.offer_slot(event, now, slot)
        return True

    def _admits(self, event: Extension) -> bool:
        """An extension event only from the processor that declared its type (its runner has
        checked the data); from anywhere else (a source) it is refused and counted."""
        if (event.publisher, event.type) in self._extensions:
            return True
        # Labelled by a configured processor's name only: any other text is "unknown", so
        # what a plugin writes there cannot grow the metric's label set.
        known = event.publisher in self._publishers
        self._inst.extension_refused.labels(
            event.publisher if known else "unknown", "undeclared"
        ).inc()
        if self._refused_log.allow("extension"):
            log.error(
                "extension_refused",
                publisher=event.publisher[:64] or None,
                type=event.type[:64],
                reason="undeclared",
                note="only a processor that declares the type in extension_events may publish it",
            )
        return False

    def _publish_durable(self, event: Event, targets: _Targets, now: float) -> bool:
        try:
            seq = self._spool.append(event, targets.names)
        except SpoolError:
            seq = None
            if self._spool_log.allow("error"):
                log.exception("spool_write_failed", kind=event.kind.value)
        if seq is None:
            self._inst.spool_refused.inc()
            for target in targets:
                target.runner.refused(event)
            return False
        for target in targets:
            target.runner.offer_spooled(event, now, seq)
        return True
