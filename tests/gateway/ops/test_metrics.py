"""The metrics registry, read back with prometheus_client's own parser."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from prometheus_client.parser import text_string_to_metric_families

from gateway.ops.metrics import DEFAULT_LATENCY_BUCKETS_S, Registry

Sample = tuple[str, dict[str, str], float]


def parse(registry: Registry) -> dict[str, list[Sample]]:
    """The samples of each family, as prometheus_client reads our text."""
    return {
        family.name: [(s.name, s.labels, s.value) for s in family.samples]
        for family in text_string_to_metric_families(registry.render())
    }


def test_counter_children_accumulate_per_label_tuple() -> None:
    registry = Registry()
    frames = registry.counter("fg_frames_total", "Frames.", ("link", "reason"))
    child = frames.labels("a", "ok")
    child.inc()
    child.inc(2.5)
    frames.labels("b", "ok").inc()
    assert frames.labels("a", "ok") is child
    assert child.value == 3.5
    assert parse(registry)["fg_frames"] == [
        ("fg_frames_total", {"link": "a", "reason": "ok"}, 3.5),
        ("fg_frames_total", {"link": "b", "reason": "ok"}, 1.0),
    ]


def test_unlabelled_metrics_are_their_own_series_and_start_at_zero() -> None:
    registry = Registry()
    starts = registry.counter("fg_starts_total", "Starts.")
    up = registry.gauge("fg_up", "Up.")
    wait = registry.histogram("fg_wait_seconds", "Wait.", buckets=(1.0,))
    assert parse(registry) == {
        "fg_starts": [("fg_starts_total", {}, 0.0)],
        "fg_up": [("fg_up", {}, 0.0)],
        "fg_wait_seconds": [
            ("fg_wait_seconds_bucket", {"le": "1.0"}, 0.0),
            ("fg_wait_seconds_bucket", {"le": "+Inf"}, 0.0),
            ("fg_wait_seconds_sum", {}, 0.0),
            ("fg_wait_seconds_count", {}, 0.0),
        ],
    }
    starts.inc()
    starts.inc(2)
    up.set(5)
    up.inc(2)
    up.dec()
    wait.observe(0.5)
    assert (starts.value, up.value) == (3.0, 6.0)
    families = parse(registry)
    assert families["fg_starts"] == [("fg_starts_total", {}, 3.0)]
    assert families["fg_up"] == [("fg_up", {}, 6.0)]
    assert ("fg_wait_seconds_count", {}, 1.0) in families["fg_wait_seconds"]


def test_gauge_children_set_inc_and_dec() -> None:
    registry = Registry()
    child = registry.gauge("fg_depth", "Depth.", ("sink",)).labels("s")
    child.set(10)
    child.inc()
    child.dec(4)
    assert child.value == 7.0
    assert parse(registry)["fg_depth"] == [("fg_depth", {"sink": "s"}, 7.0)]


def test_function_gauge_is_computed_at_each_scrape() -> None:
    registry = Registry()
    depths = {"s1": 3.0, "s2": 0.0}
    gauge = registry.gauge("fg_queue_depth", "Depth.", ("sink", "class"))
    gauge.labels("stale", "x").set(99)
    gauge.set_function(lambda: [((sink, "durable"), depth) for sink, depth in depths.items()])
    assert parse(registry)["fg_queue_depth"] == [
        ("fg_queue_depth", {"sink": "s1", "class": "durable"}, 3.0),
        ("fg_queue_depth", {"sink": "s2", "class": "durable"}, 0.0),
    ]
    depths["s2"] = 7.0
    del depths["s1"]
    assert parse(registry)["fg_queue_depth"] == [
        ("fg_queue_depth", {"sink": "s2", "class": "durable"}, 7.0)
    ]


def test_histogram_buckets_are_cumulative_with_inf_sum_and_count() -> None:
    registry = Registry()
    latency = registry.histogram("fg_latency_seconds", "Latency.", ("sink",), (0.001, 0.01))
    child = latency.labels("s")
    # 0.01 sits exactly on a bound: ``le`` means less than or equal.
    for value in (0.0005, 0.002, 0.01, 5.0):
        child.observe(value)
    samples = parse(registry)["fg_latency_seconds"]
    assert samples == [
        ("fg_latency_seconds_bucket", {"sink": "s", "le": "0.001"}, 1.0),
        ("fg_latency_seconds_bucket", {"sink": "s", "le": "0.01"}, 3.0),
        ("fg_latency_seconds_bucket", {"sink": "s", "le": "+Inf"}, 4.0),
        ("fg_latency_seconds_sum", {"sink": "s"}, pytest.approx(5.0125)),
        ("fg_latency_seconds_count", {"sink": "s"}, 4.0),
    ]


def test_a_batch_observed_at_once_scrapes_as_its_observations_one_by_one() -> None:
    values = (0.0005, 0.002, 0.01, 5.0, 0.001)
    scraped = []
    for many in (False, True):
        registry = Registry()
        child = registry.histogram("fg_l_seconds", "L.", ("sink",), (0.001, 0.01)).labels("s")
        if many:
            child.observe_many(values[:2])
            child.observe_many(iter(values[2:]))
            child.observe_many([])
        else:
            for value in values:
                child.observe(value)
        scraped.append(parse(registry)["fg_l_seconds"])
    assert scraped[0] == scraped[1]


def test_histograms_use_the_default_latency_buckets() -> None:
    registry = Registry()
    registry.histogram("fg_delay_seconds", "Delay.").observe(0.003)
    buckets = [s for s in parse(registry)["fg_delay_seconds"] if s[0].endswith("_bucket")]
    assert [float(s[1]["le"]) for s in buckets] == [*DEFAULT_LATENCY_BUCKETS_S, math.inf]
    counts = [s[2] for s in buckets]
    assert counts == sorted(counts)
    assert counts[-1] == 1.0


def test_types_and_help_are_declared() -> None:
    registry = Registry()
    registry.counter("fg_a_total", 'Say "hi" \\ then\nbreak.')
    registry.gauge("fg_b", "B.")
    registry.histogram("fg_c_seconds", "C.")
    families = {f.name: f for f in text_string_to_metric_families(registry.render())}
    assert {name: f.type for name, f in families.items()} == {
        "fg_a": "counter",
        "fg_b": "gauge",
        "fg_c_seconds": "histogram",
    }
    assert families["fg_a"].documentation == 'Say "hi" \\ then\nbreak.'


@pytest.mark.parametrize(
    ("value", "text"),
    [
        (3, "3"),
        (-0.25, "-0.25"),
        (1e300, "1e+300"),
        (math.inf, "+Inf"),
        (-math.inf, "-Inf"),
        (math.nan, "NaN"),
    ],
)
def test_values_are_written_in_go_float_syntax(value: float, text: str) -> None:
    registry = Registry()
    registry.gauge("fg_v", "V.").set(value)
    assert f"\nfg_v {text}\n" in registry.render()
    ((_, _, parsed),) = parse(registry)["fg_v"]
    assert parsed == value or (math.isnan(parsed) and math.isnan(value))


def test_registering_a_name_twice_is_refused() -> None:
    registry = Registry()
    registry.counter("fg_ok_total", "Ok.")
    with pytest.raises(ValueError, match="already registered"):
        registry.gauge("fg_ok_total", "Again.")


def test_histogram_series_names_cannot_be_reused() -> None:
    registry = Registry()
    registry.histogram("fg_h", "H.")
    with pytest.raises(ValueError, match="fg_h_count already registered"):
        registry.counter("fg_h_count", "Clash.")


@pytest.mark.parametrize("name", ["", "1abc", "fg-x", "fg x", "fg_ä", "fg_x\n"])
def test_invalid_metric_names_are_refused(name: str) -> None:
    with pytest.raises(ValueError, match="invalid metric name"):
        Registry().counter(name, "Bad.")


@pytest.mark.parametrize("label", ["", "1a", "a-b", "a:b", "ä"])
def test_invalid_label_names_are_refused(label: str) -> None:
    with pytest.raises(ValueError, match="invalid label name"):
        Registry().gauge("fg_g", "G.", (label,))


def test_reserved_and_duplicate_label_names_are_refused() -> None:
    registry = Registry()
    with pytest.raises(ValueError, match="'le' is reserved"):
        registry.histogram("fg_h", "H.", ("le",))
    with pytest.raises(ValueError, match="'__name' is reserved"):
        registry.gauge("fg_g", "G.", ("__name",))
    with pytest.raises(ValueError, match="duplicate label names"):
        registry.counter("fg_c_total", "C.", ("a", "a"))


@pytest.mark.parametrize(
    "buckets", [(), (0.1, 0.05), (0.1, 0.1), (0.1, math.inf), (math.nan,)], ids=repr
)
def test_bad_bucket_lists_are_refused(buckets: tuple[float, ...]) -> None:
    with pytest.raises(ValueError, match="strictly increasing"):
        Registry().histogram("fg_h", "H.", buckets=buckets)


def test_label_values_are_checked_on_first_use() -> None:
    registry = Registry()
    labelled = registry.counter("fg_l_total", "L.", ("a",))
    with pytest.raises(ValueError, match="takes labels"):
        labelled.labels("x", "y")
    with pytest.raises(TypeError, match="must be str"):
        labelled.labels(1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"use \.labels"):
        labelled.inc()
    assert parse(registry)["fg_l"] == []


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=40), st.text(max_size=40))
def test_any_label_value_survives_escaping(first: str, second: str) -> None:
    registry = Registry()
    registry.counter("fg_x_total", "X.", ("a", "b")).labels(first, second).inc()
    registry.histogram("fg_y_seconds", "Y.", ("a",), (1.0,)).labels(second).observe(2.0)
    families = parse(registry)
    assert families["fg_x"] == [("fg_x_total", {"a": first, "b": second}, 1.0)]
    assert ("fg_y_seconds_count", {"a": second}, 1.0) in families["fg_y_seconds"]


@settings(max_examples=200, deadline=None)
@given(st.text(st.characters(exclude_categories=("Zs", "Cc")), min_size=1, max_size=40))
def test_help_text_survives_escaping(text: str) -> None:
    registry = Registry()
    registry.gauge("fg_h", text + "\n" + text)
    (family,) = text_string_to_metric_families(registry.render())
    assert family.documentation == text + "\n" + text
