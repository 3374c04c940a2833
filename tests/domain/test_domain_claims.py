"""The claims ledger and the self-test report."""

from __future__ import annotations

import io
import math
from dataclasses import replace

import pytest

from gateway.cli import main
from gateway.domain import claims, energy, hopping, radio, sidc, targeting


def test_selftest_passes_and_lists_every_claim(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["selftest"]) == 0
    report = capsys.readouterr().out
    ledger = claims.load_claims()
    assert len(ledger) >= 17
    for claim in ledger:
        line = next(line for line in report.splitlines() if claim.id in line)
        assert line.startswith("[PASS]")
        assert "expected" in line
        assert "±" in line
    assert f"{len(ledger)}/{len(ledger)} claims hold" in report


def test_selftest_fails_on_a_mismatch(monkeypatch: pytest.MonkeyPatch) -> None:
    from gateway.domain import selftest

    wrong = tuple(replace(c, expected=c.expected + 1) for c in claims.load_claims()[:1])
    monkeypatch.setattr(selftest, "load_claims", lambda: wrong)
    out = io.StringIO()
    assert selftest.run_selftest(out) == 1
    assert "[FAIL]" in out.getvalue()


def test_every_claim_names_a_computation() -> None:
    assert {c.compute for c in claims.load_claims()} <= set(claims.COMPUTATIONS)
    assert len({c.id for c in claims.load_claims()}) == len(claims.load_claims())


def test_cep_factors_match_the_circular_normal() -> None:
    assert pytest.approx(math.sqrt(2 * math.log(2))) == targeting.CEP50_FACTOR
    assert pytest.approx(math.sqrt(2 * math.log(10))) == targeting.CEP90_FACTOR
    with pytest.raises(ValueError, match="fraction"):
        targeting.cep_factor(1.0)


def test_energy_is_physical() -> None:
    profile = energy.EnergyProfile()
    night = energy.endurance_remaining_min(400, profile, energy.EwMode.PERMISSIVE)
    day = energy.endurance_remaining_min(400, profile, energy.EwMode.PERMISSIVE, 460)
    assert day > night
    assert energy.endurance_remaining_min(400, profile, energy.EwMode.HEAVY) < night
    assert energy.endurance_remaining_min(0, profile, energy.EwMode.HEAVY) == 0


def test_link_budget_falls_6_db_per_doubling() -> None:
    budget = radio.LinkBudget()
    assert budget.received_dbm(1000) - budget.received_dbm(2000) == pytest.approx(6.0206, 1e-4)


def test_hop_plan_limits() -> None:
    plan = hopping.HopPlan((70e6, 433e6, 2.4e9, 5.8e9), 20e6, 5e-6)
    assert plan.hops_per_second == pytest.approx(200_000)
    with pytest.raises(hopping.HopPlanError, match="fastlock"):
        hopping.HopPlan(tuple(1e9 + i * 1e6 for i in range(9)), 20e6, 5e-6)
    with pytest.raises(hopping.HopPlanError, match="56 MHz"):
        hopping.HopPlan((1e9,), 60e6, 5e-6)
    with pytest.raises(hopping.HopPlanError, match="outside"):
        hopping.HopPlan((6.5e9,), 20e6, 5e-6)


def test_symbols_by_class_and_identity() -> None:
    assert sidc.symbol_codes("armour").sidc_2525c == "SHGPUCA--------"
    assert sidc.symbol_codes("tank", "suspect").sidc_2525d == "10051500001202000000"
    assert sidc.symbol_codes("uav", "unknown").cot_type == "a-u-A-M-F-Q"
    missile = sidc.symbol_codes("loitering_munition", loitering_munition="missile")
    assert missile.sidc_2525c == "SHAPWM---------"
    with pytest.raises(KeyError, match="submarine"):
        sidc.symbol_codes("submarine")
