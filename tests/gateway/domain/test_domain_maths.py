"""Energy, radio, targeting, hop plans and symbol codes: formulas against hand calculations."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from gateway.domain import energy, hopping, radio, sidc, targeting
from gateway.domain.energy import EnergyProfile, EwMode, endurance_remaining_min


class TestEnergy:
    """Endurance and solar input from the profile."""

    def test_defaults_reproduce_the_seed(self) -> None:
        profile = EnergyProfile()
        assert endurance_remaining_min(800.0, profile, EwMode.HEAVY) == 100.0  # 60·800/480
        assert energy.solar_w(profile, 460.0) == pytest.approx(46.0)  # 460·0.40·0.25

    def test_each_mode_by_hand(self) -> None:
        profile = EnergyProfile()
        assert endurance_remaining_min(400, profile, EwMode.PERMISSIVE) == pytest.approx(
            60 * 400 / 355
        )
        assert endurance_remaining_min(400, profile, EwMode.ACTIVE) == pytest.approx(60 * 400 / 415)
        # Sun lowers the net draw: 480 W − 46 W.
        assert endurance_remaining_min(400, profile, EwMode.HEAVY, 460) == pytest.approx(
            60 * 400 / 434
        )
        assert endurance_remaining_min(-5, profile, EwMode.HEAVY) == 0.0

    def test_perovskite_and_a_solar_surplus(self) -> None:
        profile = EnergyProfile(cell="perovskite", panel_area_m2=4.0, baseline_w=100.0)
        assert energy.solar_w(profile, 500.0) == pytest.approx(400.0)  # 500·4·0.20
        assert endurance_remaining_min(100, profile, EwMode.PERMISSIVE, 500.0) == math.inf

    def test_every_ew_mode_needs_an_overhead(self) -> None:
        with pytest.raises(ValidationError, match="missing EW overhead for heavy"):
            EnergyProfile(ew_overhead_w={EwMode.PERMISSIVE: 0, EwMode.ACTIVE: 60})
        with pytest.raises(ValidationError, match="at least 0 W for active"):
            EnergyProfile(
                ew_overhead_w={EwMode.PERMISSIVE: 0, EwMode.ACTIVE: -1, EwMode.HEAVY: 125}
            )

    def test_bad_inputs_are_refused(self) -> None:
        profile = EnergyProfile()
        with pytest.raises(ValueError, match="irradiance"):
            energy.solar_w(profile, -1.0)
        with pytest.raises(ValueError, match="NaN"):
            endurance_remaining_min(math.nan, profile, EwMode.HEAVY)
        with pytest.raises(ValidationError):
            EnergyProfile(cell="silicon")  # type: ignore[arg-type]

    def test_the_example_config_uses_the_defaults(self) -> None:
        """config/example.yaml spells out the energy block; it must be the documented one."""
        from pathlib import Path

        import yaml

        example = Path(__file__).parents[3] / "config" / "example.yaml"
        block = yaml.safe_load(example.read_text())["airframes"][0]["energy"]
        assert EnergyProfile(**block) == EnergyProfile()


class TestRadio:
    """Free-space link budget and camera footprint."""

    def test_free_space_path_loss_by_hand(self) -> None:
        # 20·log10(4π·50 km·2.4 GHz / c) = 134.03 dB
        assert radio.fspl_db(50_000, 2.4e9) == pytest.approx(134.0314, abs=1e-4)
        # 1 km at 1 GHz: the textbook 92.45 dB for 1 km and 1 GHz
        assert radio.fspl_db(1_000, 1e9) == pytest.approx(92.45, abs=0.01)

    def test_budget_falls_6_db_per_doubling(self) -> None:
        budget = radio.LinkBudget()
        assert budget.received_dbm(1000) - budget.received_dbm(2000) == pytest.approx(6.0206, 1e-4)

    def test_margin_reaches_zero_at_max_range(self) -> None:
        budget = radio.LinkBudget()
        assert budget.margin_db(budget.max_range_m()) == pytest.approx(0.0, abs=1e-9)
        assert budget.max_range_m() == pytest.approx(99_403, abs=1)  # 140 dB of budget

    def test_slant_range_and_footprint(self) -> None:
        assert radio.slant_range_m(300.0, 400.0) == 500.0
        # 60° cone at 100 m: radius 100·tan 30° = 57.735 m, area π·3333.3 m².
        assert radio.coverage_km2(100.0, 60.0) == pytest.approx(math.pi * 10_000 / 3 / 1e6)
        with pytest.raises(ValueError, match="field of view"):
            radio.coverage_km2(100.0, 180.0)
        with pytest.raises(ValueError, match="height"):
            radio.coverage_km2(-1.0, 90.0)
        with pytest.raises(ValueError, match="positive"):
            radio.fspl_db(0.0, 2.4e9)


class TestTargeting:
    """Root-sum-square and CEP of a circular normal."""

    def test_factors_are_rayleigh_quantiles(self) -> None:
        assert pytest.approx(math.sqrt(2 * math.log(2))) == targeting.CEP50_FACTOR
        assert pytest.approx(math.sqrt(2 * math.log(10))) == targeting.CEP90_FACTOR
        # The defining property: P(R ≤ r) = 1 − exp(−r²/2σ²).
        for p in (0.5, 0.9, 0.99):
            r = targeting.cep_factor(p)
            assert 1 - math.exp(-(r**2) / 2) == pytest.approx(p)

    def test_budget_by_hand(self) -> None:
        sigmas = [3.0, 0.56, 0.5, 2.1]  # 9 + 0.3136 + 0.25 + 4.41 = 13.9736
        assert targeting.combined_sigma(sigmas) == pytest.approx(math.sqrt(13.9736))
        assert targeting.cep50_m(sigmas) == pytest.approx(1.177410 * 3.738128, abs=1e-5)
        assert targeting.cep90_m(sigmas) == pytest.approx(2.145966 * 3.738128, abs=1e-5)

    def test_bad_inputs_are_refused(self) -> None:
        with pytest.raises(ValueError, match="fraction"):
            targeting.cep_factor(1.0)
        with pytest.raises(ValueError, match="non-negative"):
            targeting.combined_sigma([1.0, math.nan])


class TestHopping:
    """AD9361 hop plans."""

    def test_rate_with_and_without_settling(self) -> None:
        assert hopping.hops_per_second(5e-6) == pytest.approx(200_000)
        assert hopping.hops_per_second(5e-6, hopping.AD9361_PLL_SETTLE_S) == pytest.approx(50_000)
        assert hopping.beats_reactive_jammer(5e-6, 20e-6)
        assert not hopping.beats_reactive_jammer(20e-6, 20e-6)

    def test_plan_limits(self) -> None:
        plan = hopping.HopPlan((70e6, 433e6, 2.4e9, 5.8e9, 6e9), 56e6, 5e-6)
        assert plan.hops_per_second == pytest.approx(200_000)
        assert plan.beats_reactive_jammer(20e-6)
        with pytest.raises(hopping.HopPlanError, match="8 fastlock slots, found 9"):
            hopping.HopPlan(tuple(1e9 + i * 1e6 for i in range(9)), 20e6, 5e-6)
        with pytest.raises(hopping.HopPlanError, match="56 MHz"):
            hopping.HopPlan((1e9,), 60e6, 5e-6)
        with pytest.raises(hopping.HopPlanError, match=r"6500\.0 MHz is outside"):
            hopping.HopPlan((6.5e9,), 20e6, 5e-6)
        with pytest.raises(hopping.HopPlanError, match="dwell"):
            hopping.HopPlan((1e9,), 20e6, 0.0)
        with pytest.raises(hopping.HopPlanError, match="settling"):
            hopping.HopPlan((1e9,), 20e6, 5e-6, settle_s=-1.0)


class TestSidc:
    """Object class and standard identity to 2525C/2525D codes (specs/mgrs_sidc.md §4)."""

    @pytest.mark.parametrize(
        ("object_class", "hostility", "c", "d", "cot"),
        [
            ("armour", "hostile", "SHGPUCA--------", "10061000001205000000", "a-h-G-U-C-A"),
            ("tank", "hostile", "SHGPEVAT-------", "10061500001202000000", "a-h-G-E-V-A-T"),
            ("uav", "hostile", "SHAPMFQ--------", "10060100001103000000", "a-h-A-M-F-Q"),
            ("uav", "friend", "SFAPMFQ--------", "10030100001103000000", "a-f-A-M-F-Q"),
            (
                "infantry_platoon",
                "friend",
                "SFGPUCI----D---",
                "10031000141211000000",
                "a-f-G-U-C-I",
            ),
            ("tank", "suspect", "SSGPEVAT-------", "10051500001202000000", "a-s-G-E-V-A-T"),
        ],
    )
    def test_codes_match_the_spec_digest(
        self, object_class: str, hostility: sidc.Hostility, c: str, d: str, cot: str
    ) -> None:
        assert sidc.symbol_codes(object_class, hostility) == sidc.SymbolCodes(c, d, cot)

    def test_loitering_munition_options(self) -> None:
        assert sidc.symbol_codes("loitering_munition").sidc_2525c == "SHAPMFQA-------"
        missile = sidc.symbol_codes("loitering_munition", loitering_munition="missile")
        assert (missile.sidc_2525c, missile.sidc_2525d) == (
            "SHAPWM---------",
            "10060200001100000005",
        )

    def test_unknown_class_is_named(self) -> None:
        with pytest.raises(KeyError, match="submarine"):
            sidc.symbol_codes("submarine")
