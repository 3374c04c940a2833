"""Dempster-Shafer combination: the seed's figure, the rule's laws, total conflict refused."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.domain.evidence import TotalConflict, combine, simple_support
from gateway.testing import fuzz_examples

FRAME = ("uav", "loitering_munition", "helicopter", "tank", "truck")


def test_eo_080_and_ir_075_on_a_loitering_munition_combine_to_095() -> None:
    eo = simple_support(FRAME, {"loitering_munition"}, 0.80)
    ir = simple_support(FRAME, {"loitering_munition"}, 0.75)
    fused, conflict = combine(eo, ir)
    assert fused.belief({"loitering_munition"}) == pytest.approx(0.95)
    assert fused.ignorance == pytest.approx(0.05)
    assert conflict == 0.0
    assert fused.best() == ("loitering_munition", pytest.approx(0.95))


def test_disagreement_is_measured_as_conflict() -> None:
    eo = simple_support(FRAME, {"uav"}, 0.8)
    ir = simple_support(FRAME, {"tank"}, 0.6)
    fused, conflict = combine(eo, ir)
    assert conflict == pytest.approx(0.48)
    assert fused.belief({"uav"}) == pytest.approx(0.8 * 0.4 / 0.52)
    assert fused.belief({"tank"}) == pytest.approx(0.6 * 0.2 / 0.52)


def test_total_conflict_is_refused() -> None:
    with pytest.raises(TotalConflict):
        combine(simple_support(FRAME, {"uav"}, 1.0), simple_support(FRAME, {"tank"}, 1.0))


def test_a_set_of_classes_keeps_what_the_sensor_could_not_tell_apart() -> None:
    rf = simple_support(FRAME, {"uav", "loitering_munition"}, 0.7)
    eo = simple_support(FRAME, {"loitering_munition"}, 0.6)
    fused, _ = combine(rf, eo)
    assert fused.belief({"loitering_munition"}) == pytest.approx(0.6)
    assert fused.belief({"uav", "loitering_munition"}) == pytest.approx(0.88)
    assert fused.plausibility({"uav"}) == pytest.approx(0.4)


reports = st.builds(
    simple_support,
    st.just(FRAME),
    st.sets(st.sampled_from(FRAME), min_size=1, max_size=3),
    st.floats(min_value=0.0, max_value=0.99),
)


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(reports, reports, reports)
def test_the_rule_is_commutative_associative_and_normalised(a, b, c) -> None:  # type: ignore[no-untyped-def]
    ab, _ = combine(a, b)
    ba, _ = combine(b, a)
    assert ab.masses.keys() == ba.masses.keys()
    for focal, mass in ab.masses.items():
        assert mass == pytest.approx(ba.masses[focal], abs=1e-9)
    left, _ = combine(ab, c)
    right, _ = combine(a, combine(b, c)[0])
    for focal in set(left.masses) | set(right.masses):
        assert left.masses.get(focal, 0.0) == pytest.approx(right.masses.get(focal, 0.0), abs=1e-9)
    assert sum(left.masses.values()) == pytest.approx(1.0)


@settings(max_examples=fuzz_examples(200), deadline=None)
@given(reports)
def test_ignorance_changes_nothing(a) -> None:  # type: ignore[no-untyped-def]
    nothing = simple_support(FRAME, FRAME, 0.0)
    fused, conflict = combine(a, nothing)
    assert conflict == 0.0
    for focal, mass in a.masses.items():
        # Masses below EPSILON are floating-point dust and are dropped.
        assert fused.masses.get(focal, 0.0) == pytest.approx(mass, abs=1e-9)
