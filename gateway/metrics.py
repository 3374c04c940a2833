"""A small, fast Prometheus metrics registry and its text exposition (format 0.0.4).

prometheus_client is not used at run time: its per-increment locking is measurable on the
per-frame hot path, and the gateway's metrics are only touched from the event loop. A
labelled child is looked up once and kept by the caller, so an increment is one attribute
add. The tests check the output with prometheus_client's own parser.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable
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

DEFAULT_LATENCY_BUCKETS_S: tuple[float, ...] = (
    0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0,
    2.5, 5.0, 10.0,
)  # fmt: skip

_NAME = re.compile(r"^[a-zA-Z_:][a-zA-Z0-9_:]*$")
_LABEL = re.compile(r"^[a-zA-Z_][a-zA-Z0-9_]*$")


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _number(value: float) -> str:
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    if math.isnan(value):
        return "NaN"
    return repr(float(value)) if not float(value).is_integer() else str(int(value))


def _labels(names: tuple[str, ...], values: tuple[str, ...], extra: str = "") -> str:
    parts = [f'{n}="{_escape(v)}"' for n, v in zip(names, values, strict=True)]
    if extra:
        parts.append(extra)
    return "{" + ",".join(parts) + "}" if parts else ""


class CounterChild:
    """One labelled counter series."""

    __slots__ = ("value",)

    def __init__(self) -> None:
        self.value = 0.0

    def inc(self, amount: float = 1.0) -> None:
        """Add ``amount`` (never negative)."""
        self.value += amount


class GaugeChild:
    """One labelled gauge series."""

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
    """One labelled histogram series: cumulative buckets, sum and count."""

    __slots__ = ("buckets", "count", "counts", "sum")

    def __init__(self, buckets: tuple[float, ...]) -> None:
        self.buckets = buckets
        self.counts = [0] * (len(buckets) + 1)
        self.sum = 0.0
        self.count = 0

    def observe(self, value: float) -> None:
        """Record one observation."""
        self.sum += value
        self.count += 1
        for index, bound in enumerate(self.buckets):
            if value <= bound:
                self.counts[index] += 1
                return
        self.counts[-1] += 1


C = TypeVar("C", CounterChild, GaugeChild, HistogramChild)


class _Metric(Generic[C]):
    kind = ""

    def __init__(self, name: str, help_text: str, labelnames: tuple[str, ...]) -> None:
        if not _NAME.match(name):
            raise ValueError(f"invalid metric name {name!r}")
        for label in labelnames:
            if not _LABEL.match(label) or label.startswith("__"):
                raise ValueError(f"invalid label name {label!r} for {name}")
        self.name = name
        self.help = help_text
        self.labelnames = labelnames
        self.children: dict[tuple[str, ...], C] = {}

    def _new_child(self) -> C:
        raise NotImplementedError

    def labels(self, *values: str) -> C:
        """The child for these label values, created on first use; keep it on hot paths."""
        child = self.children.get(values)
        if child is None:
            if len(values) != len(self.labelnames):
                raise ValueError(f"{self.name} takes labels {self.labelnames}, got {values}")
            child = self.children[values] = self._new_child()
        return child

    def _samples(self) -> Iterable[str]:
        raise NotImplementedError

    def render(self) -> str:
        head = f"# HELP {self.name} {_escape(self.help)}\n# TYPE {self.name} {self.kind}\n"
        return head + "".join(line + "\n" for line in self._samples())


class Counter(_Metric[CounterChild]):
    """A monotonically increasing count (name ends in ``_total``)."""

    kind = "counter"

    def _new_child(self) -> CounterChild:
        return CounterChild()

    def inc(self, amount: float = 1.0) -> None:
        """Increment the unlabelled series."""
        self.labels().inc(amount)

    def _samples(self) -> Iterable[str]:
        for values, child in self.children.items():
            yield f"{self.name}{_labels(self.labelnames, values)} {_number(child.value)}"


class Gauge(_Metric[GaugeChild]):
    """A value that goes up and down, set directly or computed at scrape time."""

    kind = "gauge"

    def __init__(self, name: str, help_text: str, labelnames: tuple[str, ...]) -> None:
        super().__init__(name, help_text, labelnames)
        self._function: Callable[[], Iterable[tuple[tuple[str, ...], float]]] | None = None

    def _new_child(self) -> GaugeChild:
        return GaugeChild()

    def set(self, value: float) -> None:
        """Set the unlabelled series."""
        self.labels().set(value)

    def set_function(self, fn: Callable[[], Iterable[tuple[tuple[str, ...], float]]]) -> None:
        """Compute the series at scrape time: ``fn`` yields (label values, value) pairs."""
        self._function = fn

    def _samples(self) -> Iterable[str]:
        series = (
            ((v, c.value) for v, c in self.children.items())
            if self._function is None
            else self._function()
        )
        for values, value in series:
            yield f"{self.name}{_labels(self.labelnames, values)} {_number(value)}"


class Histogram(_Metric[HistogramChild]):
    """Observations counted into cumulative buckets."""

    kind = "histogram"

    def __init__(
        self, name: str, help_text: str, labelnames: tuple[str, ...], buckets: tuple[float, ...]
    ) -> None:
        super().__init__(name, help_text, labelnames)
        if list(buckets) != sorted(buckets) or not buckets:
            raise ValueError(f"{name}: buckets must be a sorted, non-empty tuple")
        self.buckets = buckets

    def _new_child(self) -> HistogramChild:
        return HistogramChild(self.buckets)

    def observe(self, value: float) -> None:
        """Observe into the unlabelled series."""
        self.labels().observe(value)

    def _samples(self) -> Iterable[str]:
        for values, child in self.children.items():
            cumulative = 0
            for bound, count in zip((*self.buckets, math.inf), child.counts, strict=True):
                cumulative += count
                le = f'le="{_number(bound)}"'
                yield f"{self.name}_bucket{_labels(self.labelnames, values, le)} {cumulative}"
            labels = _labels(self.labelnames, values)
            yield f"{self.name}_sum{labels} {_number(child.sum)}"
            yield f"{self.name}_count{labels} {child.count}"


class Registry:
    """The metric families of one gateway, rendered together for /metrics."""

    def __init__(self) -> None:
        self._metrics: dict[
            str, _Metric[CounterChild] | _Metric[GaugeChild] | _Metric[HistogramChild]
        ] = {}

    def _add(self, metric: C_M) -> C_M:
        if metric.name in self._metrics:
            raise ValueError(f"metric {metric.name} is already registered")
        self._metrics[metric.name] = metric
        return metric

    def counter(self, name: str, help: str, labelnames: tuple[str, ...] = ()) -> Counter:
        """Register a counter."""
        return self._add(Counter(name, help, labelnames))

    def gauge(self, name: str, help: str, labelnames: tuple[str, ...] = ()) -> Gauge:
        """Register a gauge."""
        return self._add(Gauge(name, help, labelnames))

    def histogram(
        self,
        name: str,
        help: str,
        labelnames: tuple[str, ...] = (),
        buckets: tuple[float, ...] = DEFAULT_LATENCY_BUCKETS_S,
    ) -> Histogram:
        """Register a histogram."""
        return self._add(Histogram(name, help, labelnames, buckets))

    def render(self) -> str:
        """Every metric in the Prometheus text format."""
        return "".join(metric.render() for metric in self._metrics.values())


C_M = TypeVar("C_M", Counter, Gauge, Histogram)
