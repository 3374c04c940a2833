"""The metrics registry, read back with prometheus_client's own parser."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from prometheus_client.parser import text_string_to_metric_families

from gateway.metrics import Registry


def parse(registry: Registry) -> dict[str, list[tuple[str, dict[str, str], float]]]:
    return {
        family.name: [(s.name, s.labels, s.value) for s in family.samples]
        for family in text_string_to_metric_families(registry.render())
    }


def test_counters_gauges_and_function_gauges() -> None:
    registry = Registry()
    frames = registry.counter("fg_frames_total", "Frames.", ("link",))
    frames.labels("a").inc()
    frames.labels("a").inc(2)
    frames.labels("b").inc()
    depth = registry.gauge("fg_depth", "Depth.", ("sink",))
    depth.set_function(lambda: [(("s1",), 3.0), (("s2",), 0.0)])
    up = registry.gauge("fg_up", "Up.")
    up.set(1)
    families = parse(registry)
    assert families["fg_frames"] == [
        ("fg_frames_total", {"link": "a"}, 3.0),
        ("fg_frames_total", {"link": "b"}, 1.0),
    ]
    assert families["fg_depth"] == [
        ("fg_depth", {"sink": "s1"}, 3.0),
        ("fg_depth", {"sink": "s2"}, 0.0),
    ]
    assert families["fg_up"] == [("fg_up", {}, 1.0)]


def test_histogram_buckets_are_cumulative() -> None:
    registry = Registry()
    latency = registry.histogram("fg_latency_seconds", "Latency.", ("sink",), (0.001, 0.01))
    for value in (0.0005, 0.002, 0.002, 5.0):
        latency.labels("s").observe(value)
    samples = parse(registry)["fg_latency_seconds"]
    buckets = {s[1]["le"]: s[2] for s in samples if s[0].endswith("_bucket")}
    assert buckets == {"0.001": 1.0, "0.01": 3.0, "+Inf": 4.0}
    assert ("fg_latency_seconds_count", {"sink": "s"}, 4.0) in samples
    assert ("fg_latency_seconds_sum", {"sink": "s"}, pytest.approx(5.0045)) in samples


def test_names_and_label_counts_are_checked() -> None:
    registry = Registry()
    registry.counter("fg_ok_total", "Ok.")
    with pytest.raises(ValueError, match="already registered"):
        registry.counter("fg_ok_total", "Again.")
    with pytest.raises(ValueError, match="invalid metric name"):
        registry.counter("fg bad", "Bad.")
    labelled = registry.counter("fg_l_total", "L.", ("a",))
    with pytest.raises(ValueError, match="takes labels"):
        labelled.labels("x", "y")


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=40))
def test_any_label_value_survives_escaping(value: str) -> None:
    registry = Registry()
    registry.counter("fg_x_total", "X.", ("v",)).labels(value).inc()
    ((_, labels, count),) = parse(registry)["fg_x"]
    assert labels == {"v": value}
    assert count == 1.0
