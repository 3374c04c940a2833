"""Per-class motion priors: the shipped table, overrides, and bad rows named."""

from __future__ import annotations

import pytest

from tracking import DEFAULT_CLASSES
from tracking.priors import load_priors


def test_every_class_of_the_dialect_has_a_prior_and_unknown_ones_take_other() -> None:
    priors = load_priors()
    assert set(DEFAULT_CLASSES) | {"other"} <= set(priors.names())
    assert priors["tank"].max_speed_mps < priors["loitering_munition"].max_speed_mps
    assert priors["bicycle"] == priors["other"]
    assert priors.fastest_mps == max(priors[n].max_speed_mps for n in priors.names())


def test_overrides_replace_a_row_and_keep_the_rest() -> None:
    priors = load_priors({"tank": {"max_speed_mps": 15, "accel_mps2": 0.5}})
    assert (priors["tank"].max_speed_mps, priors["tank"].accel_mps2) == (15.0, 0.5)
    assert priors["tank"].q == pytest.approx(0.25)
    assert priors["uav"] == load_priors()["uav"]


@pytest.mark.parametrize(
    ("row", "named"),
    [
        ({"max_speed_mps": -1, "accel_mps2": 1}, "max_speed_mps"),
        ({"max_speed_mps": 10}, "accel_mps2"),
        ("fast", "expected a mapping"),
    ],
)
def test_a_bad_row_is_named(row: object, named: str) -> None:
    with pytest.raises(ValueError, match=f"motion prior 'tank'.*{named}"):
        load_priors({"tank": row})
