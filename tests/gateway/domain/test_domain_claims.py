"""The claims ledger and the self-test report."""

from __future__ import annotations

import io
import re
from dataclasses import replace

import pytest

from gateway.cli import main
from gateway.domain import claims, radio, selftest
from gateway.domain.claims import ClaimsError, evaluate, load_claims, parse_claims

# The figures issue 5 requires, by identifier.
REQUIRED = {
    "FISCHER26E_AGL_UNCERTAINTY_NORDIC": 5.02,
    "FISCHER26E_AGL_UNCERTAINTY_MOUNTAINS": 20.01,
    "FISCHER26E_COVERAGE_120M": 0.045,
    "FISCHER26E_COVERAGE_700M": 1.539,
    "FISCHER26E_COVERAGE_RATIO": 34.0,
    "FISCHER26E_LINK_PENALTY_CLIMB": 0.91,
    "FISCHER26E_RX_POWER_50KM": -96.0,
    "FISCHER26E_LINK_MARGIN_50KM": 6.0,
    "FISCHER26E_HOP_RATE_VS_ELRS": 200_000,
    "FISCHER26E_HOP_BEATS_REACTIVE_JAMMER": True,
    "CEP_FROM_SIGMA_FACTOR_50": 1.1774,
    "CEP_FROM_SIGMA_FACTOR_90": 2.1460,
    "FISCHER26E_TARGET_CEP50_EXAMPLE": 4.40,
    "FISCHER26E_TARGET_CEP90_EXAMPLE": 8.02,
    "FISCHER26_ENDURANCE_HEAVY_EW_NIGHT": 100,
    "FISCHER26_SOLAR_NORDIC_SUMMER": 46,
    "SIDC_HOSTILE_GROUND_ARMOUR": "SHGPUCA--------",
}


def report() -> tuple[int, str]:
    out = io.StringIO()
    status = selftest.run_selftest(out)
    return status, out.getvalue()


class TestSelftest:
    """``run_selftest`` and the ``selftest`` command."""

    def test_passes_and_lists_every_claim_with_value_and_tolerance(self) -> None:
        status, text = report()
        assert status == 0
        ledger = load_claims()
        for claim in ledger:
            pattern = rf"^PASS  {claim.id} +(\S+) {re.escape(claim.unit)} +expected (.+)$"
            match = re.search(pattern, text, re.MULTILINE)
            assert match is not None, claim.id
            value, expected = match.groups()
            assert value == selftest.format_value(evaluate(claim).value)
            if isinstance(claim.expected, bool | str):
                assert expected == str(claim.expected)
            else:
                assert expected.endswith(f" ± {selftest.format_value(claim.tolerance)}")
        assert text.rstrip().endswith(f"{len(ledger)}/{len(ledger)} claims hold")

    def test_the_ledger_holds_the_figures_the_issue_requires(self) -> None:
        ledger = {c.id: c for c in load_claims()}
        assert {cid: ledger[cid].expected for cid in REQUIRED} == REQUIRED

    def test_notes_are_in_the_report(self) -> None:
        _, text = report()
        assert "note: Arithmetic only. One AD9361 synthesizer" in text
        assert "expected 34.0 ± 0.05" in text  # the source's digits, not 34
        assert "inputs: dwell_s=5e-06, jammer_reaction_s=2e-05" in text

    def test_a_mismatch_fails_and_is_named(self, monkeypatch: pytest.MonkeyPatch) -> None:
        first, *rest = load_claims()
        wrong = (replace(first, expected=first.expected + 1), *rest)  # type: ignore[operator]
        monkeypatch.setattr(selftest, "load_claims", lambda: wrong)
        status, text = report()
        assert status == 1
        assert re.search(rf"^FAIL  {first.id} ", text, re.MULTILINE)
        assert f"FAILED: {first.id}" in text

    def test_a_computation_that_refuses_its_inputs_fails_the_claim(
        self, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        claim = next(c for c in load_claims() if c.compute == "cep_factor")
        broken = replace(claim, inputs={"fraction": 1.5})
        monkeypatch.setattr(selftest, "load_claims", lambda: (broken,))
        status, text = report()
        assert status == 1
        assert "error: ValueError: fraction must be between 0 and 1, found 1.5" in text

    def test_the_command_exits_0(self, capsys: pytest.CaptureFixture[str]) -> None:
        assert main(["selftest"]) == 0
        assert "claims hold" in capsys.readouterr().out


class TestLedger:
    """The ledger is data, validated when it is loaded."""

    def test_ids_are_unique_and_computations_exist(self) -> None:
        ledger = load_claims()
        assert len({c.id for c in ledger}) == len(ledger)
        assert {c.compute for c in ledger} <= set(claims.COMPUTATIONS)

    def test_the_link_budget_defaults_are_the_ledger_inputs(self) -> None:
        """The 50 km claims state their parameters; the pipeline's defaults are the same."""
        claim = next(c for c in load_claims() if c.id == "FISCHER26E_LINK_MARGIN_50KM")
        budget = radio.LinkBudget()
        assert {k: getattr(budget, k) for k in claim.inputs if k != "distance_m"} == {
            k: v for k, v in claim.inputs.items() if k != "distance_m"
        }

    ENTRY = (
        "- id: X\n  what: w\n  formula: f\n  compute: cep_factor\n  inputs: {fraction: 0.5}\n"
        "  expected: 1.1774\n  tolerance: 0.0001\n  unit: σ\n  source: s\n"
    )

    def test_a_good_entry_parses(self) -> None:
        (claim,) = parse_claims(self.ENTRY)
        assert evaluate(claim).ok

    @pytest.mark.parametrize(
        ("change", "message"),
        [
            (("compute: cep_factor", "compute: nothing"), "no computation named 'nothing'"),
            (("{fraction: 0.5}", "{fraction: 0.5, extra: 1}"), "inputs do not fit cep_factor"),
            (("{fraction: 0.5}", "{fraction: 5e-1}"), "input fraction is the text '5e-1'"),
            (("  source: s\n", ""), r"missing field\(s\) source"),
            (("  source: s\n", "  source: s\n  colour: red\n"), r"unknown field\(s\) colour"),
            (("expected: 1.1774", "expected: [1]"), "expected must be a number"),
            (("expected: 1.1774", "expected: yes"), "true/false and text must match exactly"),
            (("tolerance: 0.0001", "tolerance: -1"), "tolerance must be a number at least 0"),
        ],
    )
    def test_a_bad_entry_is_named(self, change: tuple[str, str], message: str) -> None:
        with pytest.raises(ClaimsError, match=f"claim X: {message}"):
            parse_claims(self.ENTRY.replace(*change))

    def test_a_repeated_id_is_refused(self) -> None:
        with pytest.raises(ClaimsError, match="claim X: the id is used twice"):
            parse_claims(self.ENTRY + self.ENTRY)

    def test_the_ledger_must_be_a_list(self) -> None:
        with pytest.raises(ClaimsError, match="must be a list"):
            parse_claims("id: X\n")

    def test_text_and_truth_claims_compare_exactly(self) -> None:
        (claim,) = parse_claims(
            "- id: X\n  what: w\n  formula: f\n  compute: beats_reactive_jammer\n"
            "  inputs: {dwell_s: 2.0e-5, jammer_reaction_s: 2.0e-5}\n  expected: true\n"
            "  tolerance: 0\n  unit: bool\n  source: s\n"
        )
        result = evaluate(claim)
        assert (result.value, result.ok) == (False, False)
        assert not claims.ClaimResult(claim, 1.0).ok  # 1.0 is not True
