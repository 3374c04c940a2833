"""A small, fast Prometheus metrics registry and its text exposition (format 0.0.4).

prometheus_client is not used at run time: its per-increment locking is measurable on the
per-frame hot path, and the gateway's metrics are only touched from the event loop thread
(never from ``anyio.to_thread`` workers), so no lock is needed. A labelled child is looked up
once and kept by the caller, so an increment is one attribute add. The tests check the output
with prometheus_client's own parser.
"""

from __future__ import annotations

import math
import re
from bisect import bisect_left
from collections.abc import Callable, Iterable, Iterator
from itertools import pairwise
from typing import Generic, TypeVar

__all__ = [
    "DEFAULT_LATENCY_BUCKETS_S",
    "Counter",
    "CounterChild",
    "Gauge",
    "GaugeChild",
    "Histogram",
    "HistogramChild",
    "Registry",
]

# Finer than the usual 0.5 ms floor: loopback delivery latencies sit well under a
# millisecond, and bench/ingest.py interpolates p50/p99 from these buckets.
DEFAULT_LATENCY_BUCKETS_S: tuple[float, ...] = (
    0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0,
    2.5, 5.0, 10.0,
)  # fmt: skip

_METRIC_NAME = re.compile(r"[a-zA-Z_:][a-zA-Z0-9_:]*")
_LABEL_NAME = re.compile(r"[a-zA-Z_][a-zA-Z0-9_]*")
# Integral values below this print without a fraction; larger ones keep float notation so a
# huge value never becomes a few hundred digits.
_INT_LIMIT = 2.0**53


def _escape_label(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _escape_help(text: str) -> str:
    # HELP lines escape only backslash and newline; an escaped quote would be read back literally.
    return text.replace("\\", "\\\\").replace("\n", "\\n")


def _number(value: float) -> str:
    value = float(value)  # callers may hand in an int (``gauge.set(3)``)
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    if value.is_integer() and abs(value) < _INT_LIMIT:
        return str(int(value))
    return repr(value)


def _labels(names: tuple[str, ...], values: tuple[str, ...], extra: str = "") -> str:
    parts = [f'{n}="{_escape_label(v)}"' for n, v in zip(names, values, strict=True)]
    if extra:
        parts.append(extra)
    return "{" + ",".join(parts) + "}" if parts else ""


class CounterChild:
    """One counter series. ``inc`` is a bare add, so the caller must never pass a negative."""

    __slots__ = ("value",)

    def __init__(self) -> None:
        self.value = 0.0

    def inc(self, amount: float = 1.0) -> None:
        """Add ``amount`` (>= 0; not checked, this runs per frame)."""
        self.value += amount


class GaugeChild:
    """One gauge series."""

    __slots__ = ("value",)

    def __init__(self) -> None:
        self.value = 0.0

    def set(self, value: float) -> None:
        """Set the value."""
        self.value = value

    def inc(self, amount: float = 1.0) -> None:
        """Add ``amount``."""
        self.value += amount

    def dec(self, amount: float = 1.0) -> None:
        """Subtract ``amount``."""
        self.value -= amount


class HistogramChild:
    """One histogram series: per-bucket counts (the last is +Inf), sum and count."""

    __slots__ = ("bounds", "count", "counts", "sum")

    def __init__(self, bounds: tuple[float, ...]) -> None:
        self.bounds = bounds
        self.counts = [0] * (len(bounds) + 1)
        self.sum = 0.0
        self.count = 0

    def observe(self, value: float) -> None:
        """Record one observation (not NaN; not checked, this runs per event)."""
        # bisect_left finds the first bound >= value, which is Prometheus' ``le`` bucket.
        self.counts[bisect_left(self.bounds, value)] += 1
        self.sum += value
        self.count += 1

    def observe_many(self, values: Iterable[float]) -> None:
        """``observe`` each of ``values`` (a batch's: one call, the totals added once)."""
        counts, bounds = self.counts, self.bounds
        total = 0.0
        n = 0
        for value in values:
            counts[bisect_left(bounds, value)] += 1
            total += value
            n += 1
        self.sum += total
        self.count += n


C = TypeVar("C", CounterChild, GaugeChild, HistogramChild)


class _Family(Generic[C]):
    kind = ""
    reserved_labels: frozenset[str] = frozenset()
    suffixes: tuple[str, ...] = ("",)  # the sample names written are name + suffix

    def __init__(self, name: str, help_text: str, labelnames: tuple[str, ...]) -> None:
        if not _METRIC_NAME.fullmatch(name):
            raise ValueError(f"invalid metric name {name!r}: expected {_METRIC_NAME.pattern}")
        for label in labelnames:
            if not _LABEL_NAME.fullmatch(label):
                raise ValueError(
                    f"{name}: invalid label name {label!r}: expected {_LABEL_NAME.pattern}"
                )
            if label.startswith("__") or label in self.reserved_labels:
                raise ValueError(f"{name}: label name {label!r} is reserved")
        if len(set(labelnames)) != len(labelnames):
            raise ValueError(f"{name}: duplicate label names in {labelnames}")
        self.name = name
        self.help = help_text
        self.labelnames = labelnames
        self._children: dict[tuple[str, ...], C] = {}
        # An unlabelled family is its own single series, shown as 0 before first use.
        self._unlabelled: C | None = None if labelnames else self.labels()

    def _new_child(self) -> C:
        raise NotImplementedError

    def _only(self) -> C:
        if self._unlabelled is None:
            raise ValueError(f"{self.name} has labels {self.labelnames}: use .labels(...)")
        return self._unlabelled

    def labels(self, *values: str) -> C:
        """The child for these label values, created on first use; keep it on hot paths.

        Raises ``ValueError`` for the wrong number of values, ``TypeError`` for a non-str.
        """
        child = self._children.get(values)
        if child is None:
            if len(values) != len(self.labelnames):
                raise ValueError(f"{self.name} takes labels {self.labelnames}, got {values!r}")
            if not all(isinstance(v, str) for v in values):
                raise TypeError(f"{self.name}: label values must be str, got {values!r}")
            child = self._children[values] = self._new_child()
        return child

    def _samples(self) -> Iterator[str]:
        raise NotImplementedError

    def render(self) -> str:
        """This family's HELP, TYPE and sample lines."""
        head = f"# HELP {self.name} {_escape_help(self.help)}\n# TYPE {self.name} {self.kind}\n"
        return head + "".join(line + "\n" for line in self._samples())


V = TypeVar("V", CounterChild, GaugeChild)


GaugeFunction = Callable[[], Iterable[tuple[tuple[str, ...], float]]]


class _ValueFamily(_Family[V]):
    """A family whose series are one number each: counters and gauges."""

    def __init__(self, name: str, help_text: str, labelnames: tuple[str, ...]) -> None:
        super().__init__(name, help_text, labelnames)
        self._function: GaugeFunction | None = None

    def set_function(self, fn: GaugeFunction) -> None:
        """Compute the series at scrape time instead of storing them.

        ``fn`` runs on the event loop during ``render`` and yields (label values, value)
        pairs, one per series; label values must match ``labelnames`` in number. Series
        set through ``labels`` are no longer rendered. A counter's function must never
        return less than it did before.
        """
        self._function = fn

    def inc(self, amount: float = 1.0) -> None:
        """Add to an unlabelled metric; ``ValueError`` if it has labels."""
        self._only().value += amount

    @property
    def value(self) -> float:
        """The value of an unlabelled metric; ``ValueError`` if it has labels."""
        return self._only().value

    def _series(self) -> Iterable[tuple[tuple[str, ...], float]]:
        if self._function is not None:
            return self._function()
        return ((values, child.value) for values, child in self._children.items())

    def _samples(self) -> Iterator[str]:
        for values, value in self._series():
            yield f"{self.name}{_labels(self.labelnames, values)} {_number(value)}"


class Counter(_ValueFamily[CounterChild]):
    """A monotonically increasing count; by convention the name ends in ``_total``."""

    kind = "counter"

    def _new_child(self) -> CounterChild:
        return CounterChild()


class Gauge(_ValueFamily[GaugeChild]):
    """A value that goes up and down, stored or computed at scrape time."""

    kind = "gauge"

    def _new_child(self) -> GaugeChild:
        return GaugeChild()

    def set(self, value: float) -> None:
        """Set an unlabelled gauge; ``ValueError`` if it has labels."""
        self._only().value = value

    def dec(self, amount: float = 1.0) -> None:
        """Subtract from an unlabelled gauge."""
        self._only().value -= amount


class Histogram(_Family[HistogramChild]):
    """Observations counted into cumulative buckets, with their sum and count."""

    kind = "histogram"
    reserved_labels = frozenset({"le"})
    suffixes = ("", "_bucket", "_sum", "_count")

    def __init__(
        self, name: str, help_text: str, labelnames: tuple[str, ...], buckets: tuple[float, ...]
    ) -> None:
        finite = all(math.isfinite(b) for b in buckets)
        increasing = all(a < b for a, b in pairwise(buckets))
        if not buckets or not finite or not increasing:
            raise ValueError(
                f"{name}: buckets must be finite and strictly increasing (+Inf is added), "
                f"got {buckets!r}"
            )
        self.buckets = tuple(float(b) for b in buckets)
        super().__init__(name, help_text, labelnames)

    def _new_child(self) -> HistogramChild:
        return HistogramChild(self.buckets)

    def observe(self, value: float) -> None:
        """Observe into an unlabelled histogram; ``ValueError`` if it has labels."""
        self._only().observe(value)

    def _samples(self) -> Iterator[str]:
        # Bounds keep float notation (le="1.0"), as prometheus_client writes them, so series
        # from either exporter match in PromQL.
        bounds = [f'le="{b!r}"' for b in self.buckets] + ['le="+Inf"']
        for values, child in self._children.items():
            cumulative = 0
            for le, count in zip(bounds, child.counts, strict=True):
                cumulative += count
                yield f"{self.name}_bucket{_labels(self.labelnames, values, le)} {cumulative}"
            labels = _labels(self.labelnames, values)
            yield f"{self.name}_sum{labels} {_number(child.sum)}"
            yield f"{self.name}_count{labels} {child.count}"


F = TypeVar("F", Counter, Gauge, Histogram)


class Registry:
    """The metric families of one gateway, rendered together for /metrics."""

    def __init__(self) -> None:
        self._families: list[Counter | Gauge | Histogram] = []
        self._names: set[str] = set()

    def _add(self, family: F) -> F:
        # Also refuse a family whose samples would collide, e.g. a counter "h_count" next to a
        # histogram "h".
        names = {family.name + suffix for suffix in family.suffixes}
        if clash := names & self._names:
            raise ValueError(f"metric {family.name}: {', '.join(sorted(clash))} already registered")
        self._names |= names
        self._families.append(family)
        return family

    def counter(self, name: str, help: str, labelnames: tuple[str, ...] = ()) -> Counter:
        """Register a counter; ``ValueError`` for a bad or already registered name."""
        return self._add(Counter(name, help, labelnames))

    def gauge(self, name: str, help: str, labelnames: tuple[str, ...] = ()) -> Gauge:
        """Register a gauge; ``ValueError`` for a bad or already registered name."""
        return self._add(Gauge(name, help, labelnames))

    def histogram(
        self,
        name: str,
        help: str,
        labelnames: tuple[str, ...] = (),
        buckets: tuple[float, ...] = DEFAULT_LATENCY_BUCKETS_S,
    ) -> Histogram:
        """Register a histogram; ``ValueError`` for a bad name, label or bucket list."""
        return self._add(Histogram(name, help, labelnames, buckets))

    def render(self) -> str:
        """Every family in registration order, in the Prometheus text format 0.0.4."""
        return "".join(family.render() for family in self._families)
