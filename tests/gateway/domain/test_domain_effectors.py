"""Effector recommendation: range bands, reach, danger-close deconfliction, a checked table."""

from __future__ import annotations

import pytest

from gateway.domain.effectors import load_effector_table, recommend
from gateway.errors import ConfigError


def test_the_shipped_table_loads_and_recommends_by_range_band() -> None:
    table = load_effector_table()
    close = recommend(table, "loitering_munition", 1800.0, nearest_blue_m=5000.0)
    assert [r.effector for r in close] == [
        "TRACKFIRE_30MM", "TRIDON_MK2_40MM", "EW_COUNTERMEASURES",
    ]  # fmt: skip
    assert all(r.deconfliction_clear for r in close)
    far = recommend(table, "loitering_munition", 6000.0, nearest_blue_m=None)
    assert [r.effector for r in far] == ["EW_COUNTERMEASURES", "GIRAFFE_1X_DESIGNATE"]
    assert recommend(table, "tank", 1000.0, nearest_blue_m=None) == []


def test_a_friendly_unit_inside_danger_close_is_not_clear_for_that_effector_only() -> None:
    table = load_effector_table()
    recs = {r.effector: r for r in recommend(table, "loitering_munition", 1800.0, 500.0)}
    assert not recs["TRIDON_MK2_40MM"].deconfliction_clear  # 500 m < 600 m danger close
    assert recs["TRACKFIRE_30MM"].deconfliction_clear  # 500 m > 400 m
    assert recs["EW_COUNTERMEASURES"].deconfliction_clear


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "effectors: {A: {max_range_m: 1, danger_close_m: 0}}\n"
            "recommendations: {uav: [{up_to_m: 1, effectors: [B]}]}\n",
            "unknown effector 'B'",
        ),
        (
            "effectors: {A: {max_range_m: 9, danger_close_m: 0}}\n"
            "recommendations: {uav: [{up_to_m: 5, effectors: [A]},\n"
            "                        {up_to_m: 2, effectors: [A]}]}\n",
            "range bands must ascend",
        ),
    ],
)
def test_a_wrong_table_is_a_config_error(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_effector_table(text, "mine.yaml")
