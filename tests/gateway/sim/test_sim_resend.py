"""The airframe's re-send store: bounded, jittered exponential backoff, a capped rate, acks."""

from __future__ import annotations

import itertools
import math
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.fleet.dialect import (
    FISCHER_DETECTION_ACK_RESULT_DUPLICATE,
    FISCHER_DETECTION_ACK_RESULT_HELD,
    FischerDetection,
    FischerDetectionAck,
    fischer_detection,
    fischer_detection_ack,
)
from gateway.sim.resend import ResendPolicy, ResendStore

SYSID = 7
T0_US = 1_763_800_000_000_000


def detection(n: int, time_usec: int = T0_US) -> FischerDetection:
    return fischer_detection(time_usec + n, n, 658_352_000, 216_886_000, 150.0, 8.0, 1, 1, 91)


def ack_of(
    msg: FischerDetection,
    *,
    sysid: int = SYSID,
    component: int = 1,
    result: int = FISCHER_DETECTION_ACK_RESULT_HELD,
) -> FischerDetectionAck:
    return fischer_detection_ack(msg.time_usec, msg.detection_id, sysid, component, result)


def heard(store: ResendStore) -> ResendStore:
    """The store after the gateway acknowledged something (so re-sending has started)."""
    store.acknowledge(ack_of(detection(10**9)))
    return store


def resend_times(store: ResendStore, until_s: float) -> list[tuple[float, int]]:
    """(time, detection_id) of every re-send, stepping exactly to each due time."""
    out = []
    while (now := store.next_due_s()) <= until_s:
        out += [(now, int(m.detection_id)) for m in store.take_due(now)]
    return out


class TestResendPolicy:
    """The policy's defaults, its schedule and its validation."""

    def test_defaults_are_one_second_doubling_to_eight_and_ten_thousand_held(self) -> None:
        policy = ResendPolicy()
        assert (policy.first_s, policy.max_s, policy.capacity) == (1.0, 8.0, 10_000)
        assert [policy.nominal_s(n) for n in range(1, 7)] == [1.0, 2.0, 4.0, 8.0, 8.0, 8.0]
        assert policy.nominal_s(10**6) == 8.0  # no overflow however long the outage

    @pytest.mark.parametrize(
        ("kwargs", "field"),
        [
            ({"first_s": 0.0}, "first_s"),
            ({"first_s": math.nan}, "first_s"),
            ({"first_s": 2.0, "max_s": 1.0}, "max_s"),
            ({"jitter": 1.0}, "jitter"),
            ({"jitter": -0.1}, "jitter"),
            ({"rate_hz": 0.0}, "rate_hz"),
            ({"rate_hz": math.inf}, "rate_hz"),
            ({"capacity": 0}, "capacity"),
        ],
    )
    def test_out_of_range_values_are_refused_naming_the_field(
        self, kwargs: dict[str, float], field: str
    ) -> None:
        with pytest.raises(ValueError, match=rf"ResendPolicy\.{field}: expected"):
            ResendPolicy(**kwargs)  # type: ignore[arg-type]

    @given(
        attempt=st.integers(min_value=1, max_value=200),
        draw=st.floats(min_value=0.0, max_value=1.0, exclude_max=True),
        jitter=st.floats(min_value=0.0, max_value=0.99),
    )
    def test_a_jittered_delay_is_never_later_than_nominal_nor_earlier_than_its_floor(
        self, attempt: int, draw: float, jitter: float
    ) -> None:
        policy = ResendPolicy(jitter=jitter)
        nominal = policy.nominal_s(attempt)
        assert nominal * (1 - jitter) - 1e-12 <= policy.delay_s(attempt, draw) <= nominal


class TestResendStore:
    """Held until acknowledged; re-sent on schedule, at a capped rate; bounded."""

    def test_without_jitter_the_resends_follow_one_two_four_eight_eight(self) -> None:
        store = heard(ResendStore(SYSID, ResendPolicy(jitter=0.0)))
        msg = detection(1)
        store.add(msg, 0.0)
        assert store.take_due(0.999) == []
        assert [t for t, _ in resend_times(store, 31.0)] == [1.0, 3.0, 7.0, 15.0, 23.0, 31.0]
        assert store.counts.resent == 6
        assert (1, msg.time_usec) in store

    @settings(max_examples=50)
    @given(seed=st.integers(0, 2**32 - 1), jitter=st.floats(0.0, 0.9))
    def test_jittered_intervals_stay_within_their_bounds(self, seed: int, jitter: float) -> None:
        policy = ResendPolicy(first_s=1.0, max_s=8.0, jitter=jitter)
        store = heard(ResendStore(SYSID, policy, rng=random.Random(seed)))
        store.add(detection(1), 0.0)
        sent = [0.0] + [t for t, _ in resend_times(store, 60.0)]
        intervals = [b - a for a, b in itertools.pairwise(sent)]
        assert len(intervals) >= 6
        for n, interval in enumerate(intervals, start=1):
            nominal = policy.nominal_s(n)
            assert nominal * (1 - jitter) - 1e-9 <= interval <= nominal + 1e-9

    def test_detections_lost_together_are_not_resent_together(self) -> None:
        store = heard(ResendStore(SYSID, ResendPolicy(rate_hz=1e6), rng=random.Random(1)))
        for n in range(1, 101):
            store.add(detection(n), 0.0)
        first = {}
        for t, detection_id in resend_times(store, 1.0):
            first.setdefault(detection_id, t)
        assert len(first) == 100
        assert len(set(first.values())) > 90  # spread over [0.8, 1.0] s, not one burst
        assert min(first.values()) >= 0.8
        assert max(first.values()) <= 1.0

    @settings(max_examples=30)
    @given(
        backlog=st.integers(1, 400),
        rate_hz=st.floats(1.0, 100.0),
        seed=st.integers(0, 2**16),
    )
    def test_resends_never_exceed_the_rate_cap_however_large_the_backlog(
        self, backlog: int, rate_hz: float, seed: int
    ) -> None:
        store = heard(ResendStore(SYSID, ResendPolicy(rate_hz=rate_hz), rng=random.Random(seed)))
        for n in range(1, backlog + 1):
            store.add(detection(n), 0.0)
        times = [t for t, _ in resend_times(store, 30.0)]
        assert all(b - a >= 1 / rate_hz - 1e-9 for a, b in itertools.pairwise(times))
        # Every held detection still gets its turn: the backlog drains at the capped rate.
        assert len(times) >= min(backlog, math.floor((30.0 - 1.0) * rate_hz))

    def test_an_ack_removes_the_detection_and_a_duplicate_ack_is_harmless(self) -> None:
        store = heard(ResendStore(SYSID, ResendPolicy(jitter=0.0)))
        one, two = detection(1), detection(2)
        store.add(one, 0.0)
        store.add(two, 0.0)
        assert store.acknowledge(ack_of(one))
        assert not store.acknowledge(ack_of(one, result=FISCHER_DETECTION_ACK_RESULT_DUPLICATE))
        assert len(store) == 1
        assert (1, one.time_usec) not in store
        assert [d for _, d in resend_times(store, 3.0)] == [2, 2]
        assert (store.counts.acknowledged, store.counts.acks_unmatched) == (1, 2)

    def test_identity_is_detection_id_and_time_usec_together(self) -> None:
        store = heard(ResendStore(SYSID, ResendPolicy()))
        msg = detection(1)
        store.add(msg, 0.0)
        wrong_time = fischer_detection_ack(msg.time_usec + 1, 1, SYSID, 1, 0)
        wrong_id = fischer_detection_ack(msg.time_usec, 2, SYSID, 1, 0)
        assert not store.acknowledge(wrong_time)
        assert not store.acknowledge(wrong_id)
        assert len(store) == 1

    @pytest.mark.parametrize(
        ("sysid", "component", "result"),
        [(SYSID + 1, 1, 0), (0, 1, 0), (SYSID, 2, 0), (SYSID, 1, 2), (SYSID, 1, 255)],
        ids=["other-system", "broadcast-system", "other-component", "result-2", "result-255"],
    )
    def test_acks_for_another_airframe_or_with_an_unknown_result_are_ignored(
        self, sysid: int, component: int, result: int
    ) -> None:
        store = ResendStore(SYSID, ResendPolicy())
        msg = detection(1)
        store.add(msg, 0.0)
        assert not store.acknowledge(ack_of(msg, sysid=sysid, component=component, result=result))
        assert len(store) == 1
        assert store.counts.acks_ignored == 1
        assert not store.has_heard_ack  # an ignored ack does not start re-sending either

    def test_an_ack_to_all_components_counts(self) -> None:
        store = ResendStore(SYSID, ResendPolicy())
        msg = detection(1)
        store.add(msg, 0.0)
        assert store.acknowledge(ack_of(msg, component=0))

    def test_when_full_the_oldest_is_dropped_and_counted(self) -> None:
        store = heard(ResendStore(SYSID, ResendPolicy(capacity=3)))
        msgs = [detection(n) for n in range(1, 6)]
        for t, msg in enumerate(msgs):
            store.add(msg, float(t))
        assert len(store) == 3
        assert store.counts.dropped == 2
        assert [(m.detection_id, m.time_usec) in store for m in msgs] == [
            False,
            False,
            True,
            True,
            True,
        ]
        # A late ack for a dropped detection is unmatched, not an error.
        assert not store.acknowledge(ack_of(msgs[0]))
        assert store.counts.acks_unmatched == 2  # with heard()'s

    def test_a_resend_is_the_very_same_detection(self) -> None:
        store = heard(ResendStore(SYSID, ResendPolicy(jitter=0.0)))
        msg = detection(1)
        store.add(msg, 0.0)
        (again,) = store.take_due(1.0)
        assert again is msg

    def test_nothing_is_resent_before_the_gateway_is_heard_to_acknowledge(self) -> None:
        """A gateway without acknowledgements never gets duplicates; once one is heard, what
        was held all along is re-sent (overdue ones first, at the capped rate)."""
        store = ResendStore(SYSID, ResendPolicy(jitter=0.0, rate_hz=10.0))
        old, new = detection(1), detection(2)
        store.add(old, 0.0)
        store.add(new, 5.0)
        assert store.next_due_s() == math.inf
        assert store.take_due(100.0) == []
        store.acknowledge(ack_of(new))
        assert store.has_heard_ack
        assert store.next_due_s() == 1.0  # overdue: due at once
        assert store.take_due(100.0) == [old]

    def test_without_needs_ack_heard_resends_start_at_once(self) -> None:
        store = ResendStore(SYSID, ResendPolicy(jitter=0.0, needs_ack_heard=False))
        store.add(detection(1), 0.0)
        assert store.next_due_s() == 1.0

    def test_no_policy_holds_nothing_but_counts(self) -> None:
        store = ResendStore(SYSID, None)
        store.add(detection(1), 0.0)
        assert len(store) == 0
        assert store.counts.sent == 1
        assert store.take_due(100.0) == []
        assert store.next_due_s() == math.inf


@st.composite
def operations(draw: st.DrawFn) -> list[tuple[str, int]]:
    """Adds of detections 1..40, acks (some of never-sent ones), and time steps."""
    return draw(
        st.lists(
            st.one_of(
                st.tuples(st.just("add"), st.integers(1, 40)),
                st.tuples(st.just("ack"), st.integers(1, 45)),
                st.tuples(st.just("wait"), st.integers(0, 3000)),
            ),
            max_size=300,
        )
    )


@settings(max_examples=100)
@given(ops=operations(), capacity=st.integers(1, 20), seed=st.integers(0, 2**16))
def test_every_detection_is_held_acknowledged_or_dropped_never_lost_silently(
    ops: list[tuple[str, int]], capacity: int, seed: int
) -> None:
    policy = ResendPolicy(first_s=0.1, max_s=0.8, rate_hz=50.0, capacity=capacity)
    store = heard(ResendStore(SYSID, policy, rng=random.Random(seed)))
    now, added, last_resend = 0.0, set(), -math.inf
    for op, value in ops:
        if op == "add" and value not in added:
            added.add(value)
            store.add(detection(value), now)
        elif op == "ack":
            store.acknowledge(ack_of(detection(value)))
        elif op == "wait":
            now += value / 1000
            for _ in store.take_due(now):
                assert now - last_resend >= 1 / policy.rate_hz - 1e-9
                last_resend = now
        assert len(store) <= capacity
    counts = store.counts
    assert counts.sent == len(added)
    assert counts.acknowledged + counts.dropped + len(store) == len(added)
