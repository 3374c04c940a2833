"""Simulator scenarios: the file format, the schedule's geometry and noise, the shipped files."""

from __future__ import annotations

import itertools
import math
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

from gateway.domain.geodesy import distance_bearing
from gateway.errors import ConfigError
from gateway.sim.runner import DetectionFeed, blue_force_cot
from gateway.sim.scenario import load_scenario, load_scenario_text, shipped_scenarios
from gateway.sim.schedule import (
    BlueReport,
    SimDetection,
    airframe_position,
    blue_reports,
    detections,
    events_at,
    schedule,
    sensor_looks,
    target_tracks,
)
from sinks.cot.validate import parse_cot

BASE = """\
name: test
duration_s: 20
seed: 7
airframes:
  - id: A1
    sysid: 1
    orbit:
      {centre_lat_deg: 65.82, centre_lon_deg: 21.69, radius_m: 500, alt_msl_m: 400, speed_mps: 20}
    sensors:
      - {sensor: eo, range_m: RANGE, confidence: 0.8, sigma_h_m: SIGMA, rate_hz: 1}
targets:
  - id: T
    class: tank
    subtype: T-72B3
    path: [{lat_deg: 65.83, lon_deg: 21.69, alt_msl_m: 50}]
"""


def scenario_text(range_m: float = 5000, sigma_m: float = 10) -> str:
    return BASE.replace("RANGE", str(range_m)).replace("SIGMA", str(sigma_m))


def dets(scenario_text_: str) -> list[SimDetection]:
    s = load_scenario_text(scenario_text_)
    return [d for a in s.airframes for d in detections(s, a)]


class TestModel:
    """The file is validated once, with errors naming the file, key and line."""

    def test_unknown_key_is_named_with_its_line(self) -> None:
        text = scenario_text().replace("rate_hz: 1}", "rate_hz: 1, rnage: 4}")
        with pytest.raises(ConfigError) as caught:
            load_scenario_text(text, "my.yaml")
        (issue,) = caught.value.issues
        assert (issue.source, issue.line) == ("my.yaml", 10)
        assert issue.key_path == "airframes[0].sensors[0].rnage"
        assert "did you mean 'range_m'" in issue.message

    def test_bad_values_and_duplicates_each_reported(self) -> None:
        text = (
            scenario_text()
            + "  - {id: T, class: tank, path: [{lat_deg: 99, lon_deg: 0, alt_msl_m: 0}]}\n"
        )
        text = text.replace("confidence: 0.8", "confidence: 1.5").replace("seed: 7", "seed: .nan")
        with pytest.raises(ConfigError) as caught:
            load_scenario_text(text, "x.yaml")
        where = {issue.key_path: issue.line for issue in caught.value.issues}
        assert where["seed"] == 3
        assert where["airframes[0].sensors[0]"] == 10
        assert where["targets[1].id"] == 16
        assert where["targets[1].path[0].lat_deg"] == 16

    def test_subtype_is_at_most_16_ascii(self) -> None:
        with pytest.raises(ConfigError, match="subtype"):
            load_scenario_text(scenario_text().replace("T-72B3", "T-72B3-MODERNISED-2016"))

    def test_missing_file_names_the_shipped_scenarios(self, tmp_path: Path) -> None:
        with pytest.raises(ConfigError, match="brigade"):
            load_scenario(tmp_path / "absent.yaml")


class TestSchedule:
    """Detections follow the geometry; noise is seeded and has the stated sigma."""

    def test_same_seed_same_detections(self) -> None:
        assert dets(scenario_text()) == dets(scenario_text())
        other = dets(scenario_text().replace("seed: 7", "seed: 8"))
        assert [d.lat_deg for d in other] != [d.lat_deg for d in dets(scenario_text())]

    def test_out_of_range_gives_none(self) -> None:
        # The target is about 1.1 km north of the orbit's centre; the orbit's radius is 500 m.
        assert dets(scenario_text(range_m=400)) == []
        assert len(dets(scenario_text(range_m=2000))) == 21

    def test_range_is_from_the_airframe_position(self) -> None:
        s = load_scenario_text(scenario_text(range_m=1100))
        for t_s in range(21):
            lat, lon = airframe_position(s.airframes[0], t_s)
            distance = distance_bearing(lat, lon, 65.83, 21.69)[0]
            seen = [e for e in events_at(s, t_s) if isinstance(e, SimDetection)]
            assert bool(seen) == (distance <= 1100)

    def test_noise_has_sigma_per_axis(self) -> None:
        text = scenario_text(sigma_m=20).replace("duration_s: 20", "duration_s: 2000")
        found = dets(text)
        assert len(found) == 2001
        north = [distance_bearing(65.83, 21.69, d.lat_deg, 21.69)[0] for d in found]
        signed = [n if d.lat_deg >= 65.83 else -n for n, d in zip(north, found, strict=True)]
        assert abs(statistics.fmean(signed)) < 2.0
        assert 18.0 < statistics.pstdev(signed) < 22.0

    def test_detection_ids_count_up_per_airframe(self) -> None:
        assert [d.detection_id for d in dets(scenario_text())] == list(range(1, 22))

    def test_column_vehicles_are_spaced_along_the_road(self) -> None:
        s = load_scenario("t72-column")
        tracks = target_tracks(s)
        assert [t.id for t in tracks] == ["COL-1", "COL-2", "COL-3", "COL-4"]
        positions = [t.position(60.0) for t in tracks]
        assert all(p is not None for p in positions)
        gaps = [
            distance_bearing(a[0], a[1], b[0], b[1])[0]
            for a, b in itertools.pairwise(positions)
            if a is not None and b is not None
        ]
        assert gaps == pytest.approx([50.0] * 3, abs=0.5)
        # Vehicle 4 is 150 m behind the lead: it enters the road 15 s after it (10 m/s).
        assert tracks[3].position(14.9) is None
        assert tracks[3].position(15.1) is not None

    def test_a_munition_vanishes_at_the_end_of_its_path(self) -> None:
        (lm1, _) = target_tracks(load_scenario("loitering-munitions"))
        assert lm1.position(109.0) is not None
        assert lm1.position(111.0) is None

    def test_blue_forces_report_at_their_interval(self) -> None:
        s = load_scenario("brigade")
        reports = list(blue_reports(s))
        by_unit: dict[str, list[float]] = {}
        for r in reports:
            by_unit.setdefault(r.callsign, []).append(r.t_s)
        assert set(by_unit) == {"VIDAR 1", "VIDAR 2", "VIDAR 3"}
        for times in by_unit.values():
            assert times == pytest.approx([5.0 * k for k in range(25)])
        moving = [r for r in reports if r.callsign == "VIDAR 3"]
        moved = distance_bearing(
            moving[0].lat_deg, moving[0].lon_deg, moving[-1].lat_deg, moving[-1].lon_deg
        )[0]
        assert moved == pytest.approx(4.0 * 120, rel=0.01)

    def test_schedule_is_in_time_order(self) -> None:
        times = [e.t_s for e in schedule(load_scenario("brigade"))]
        assert times == sorted(times)


class TestSensors:
    """Each sensor of an airframe looks with its own kind, rate and range."""

    def test_an_airframe_with_two_sensors_reports_from_both(self) -> None:
        text = scenario_text().replace(
            "      - {sensor: eo, range_m: 5000, confidence: 0.8, sigma_h_m: 10, rate_hz: 1}\n",
            "      - {sensor: eo, range_m: 5000, confidence: 0.8, sigma_h_m: 10, rate_hz: 1}\n"
            "      - {sensor: ir, range_m: 5000, confidence: 0.7, sigma_h_m: 20, rate_hz: 2}\n",
        )
        scenario = load_scenario_text(text)
        (airframe,) = scenario.airframes
        looks = list(sensor_looks(airframe, 10.0))
        assert {s for _, s, _ in looks} == {0, 1}
        # Looks at 0..10 s inclusive: 11 at 1 Hz, 21 at 2 Hz.
        assert [sum(1 for _, s, _ in looks if s == i) for i in (0, 1)] == [11, 21]
        seen = dets(text)
        by_sensor = {d.sensor: [x for x in seen if x.sensor == d.sensor] for d in seen}
        assert set(by_sensor) == {"eo", "ir"}
        assert {d.sigma_h_m for d in by_sensor["eo"]} == {10.0}
        assert {d.sigma_h_m for d in by_sensor["ir"]} == {20.0}


class TestShipped:
    """The shipped scenarios load and say what their comments say."""

    def test_all_load(self) -> None:
        names = shipped_scenarios()
        assert names == [
            "brigade",
            "crossing-columns",
            "danger-close",
            "loitering-munitions",
            "parked-vehicles",
            "shared-target",
            "swarm",
            "t72-column",
        ]
        for name in names:
            assert load_scenario(name).name == name
            assert load_scenario(f"{name}.yaml").name == name

    def test_loitering_munitions_eo_080_and_ir_075_for_each(self) -> None:
        s = load_scenario("loitering-munitions")
        seen = {
            (e.airframe, e.sensor, e.target, e.confidence, e.subtype)
            for e in schedule(s)
            if isinstance(e, SimDetection)
        }
        assert seen == {
            ("F26E-001", "eo", "LM-1", 0.80, "LANCET-3"),
            ("F26E-001", "eo", "LM-2", 0.80, "LANCET-3"),
            ("F26E-002", "ir", "LM-1", 0.75, "LANCET-3"),
            ("F26E-002", "ir", "LM-2", 0.75, "LANCET-3"),
        }

    def test_brigade_munition_passes_danger_close_of_a_platoon(self) -> None:
        s = load_scenario("brigade")
        lm1 = target_tracks(s)[0]
        closest = min(
            distance_bearing(p[0], p[1], 65.83159, 21.70677)[0]
            for t in range(1200)
            if (p := lm1.position(t / 10)) is not None
        )
        assert 250 < closest < 300
        (battery,) = s.batteries
        assert battery.effectors == (
            "TRIDON_MK2_40MM",
            "TRACKFIRE_30MM",
            "EW_COUNTERMEASURES",
            "GIRAFFE_1X_DESIGNATE",
        )


class TestEncoding:
    """What goes on the wire: FISCHER_DETECTION fields and CoT the gateway's parser accepts."""

    def test_feed_encodes_detections_with_the_observation_time(self) -> None:
        s = load_scenario_text(scenario_text())
        flyer = s.airframes[0]
        feed = DetectionFeed(s, flyer, s.duration_s, lambda _t: (65.83, 21.70))
        assert feed.next_due_s() == 0.0
        (msg,) = feed.messages_at(0.0, 1_700_000_000.5)
        assert msg.time_usec == 1_700_000_000_500_000
        assert (msg.class_id, msg.sensor, msg.confidence) == (1, 0, 80)
        assert msg.subtype == b"T-72B3"
        assert feed.next_due_s() == 1.0

    def test_feed_tells_each_sensor_frame_its_size(self) -> None:
        """The detections of one look are one sensor frame: each says how many it holds."""
        text = scenario_text(range_m=2000).replace(
            "    path: [{lat_deg: 65.83, lon_deg: 21.69, alt_msl_m: 50}]",
            "    path: [{lat_deg: 65.83, lon_deg: 21.69, alt_msl_m: 50}]\n"
            "  - {id: T2, class: tank, path: [{lat_deg: 65.831, lon_deg: 21.69, alt_msl_m: 50}]}\n"
            "  - {id: T3, class: tank, path: [{lat_deg: 65.86, lon_deg: 21.69, alt_msl_m: 50}]}",
        )
        s = load_scenario_text(text)
        feed = DetectionFeed(s, s.airframes[0], s.duration_s, lambda _t: (65.83, 21.70))
        messages = feed.messages_at(0.0, 1_700_000_000.0)
        assert [m.frame_size for m in messages] == [2, 2]  # T3 is out of range

    def test_blue_force_cot_parses_as_a_friendly_position(self) -> None:
        from datetime import UTC, datetime, timedelta

        now = datetime.now(UTC)
        report = BlueReport(0.0, "BLUE-1", "VIDAR 1", "a-f-G-U-C-I", 65.83, 21.70, 42.0)
        cot = parse_cot(blue_force_cot(report, now, timedelta(seconds=30)), strict=True)
        assert (cot.uid, cot.type, cot.callsign) == ("BLUE-1", "a-f-G-U-C-I", "VIDAR 1")
        assert (cot.lat, cot.lon) == pytest.approx((65.83, 21.70))
        assert math.isclose(cot.hae, 42.0 + 22.0, abs_tol=3.0)  # EGM96 N ≈ 22 m at Boden


def simulate(*args: str) -> subprocess.CompletedProcess[str]:
    """The CLI in a child process: it configures logging, which a test process must not."""
    command = [sys.executable, "-m", "gateway", "simulate", "--to", "udp://127.0.0.1:9", *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=60, check=False)

    def test_swarm_is_six_munitions_80_to_150_m_apart(self) -> None:
        tracks = target_tracks(load_scenario("swarm"))
        assert [t.target.object_class for t in tracks] == ["loitering_munition"] * 6
        for t_s in (0.0, 45.0, 90.0):
            where = [t.position(t_s) for t in tracks]
            gaps = [
                distance_bearing(a[0], a[1], b[0], b[1])[0]
                for a, b in itertools.pairwise(w for w in where if w is not None)
            ]
            assert len(gaps) == 5
            assert all(78 < gap < 152 for gap in gaps), gaps

    def test_parked_vehicles_stand_30_m_apart_seen_with_sigma_15_to_20(self) -> None:
        s = load_scenario("parked-vehicles")
        tracks = target_tracks(s)
        where = [t.position(50.0) for t in tracks]
        assert where == [t.position(0.0) for t in tracks]  # stationary
        gaps = [
            distance_bearing(a[0], a[1], b[0], b[1])[0]
            for a, b in itertools.pairwise(w for w in where if w is not None)
        ]
        assert gaps == pytest.approx([30.0] * 4, abs=0.5)
        assert {sensor.sigma_h_m for a in s.airframes for sensor in a.sensors} == {15, 20}

    def test_shared_target_is_seen_by_three_airframes(self) -> None:
        seen = {
            e.airframe
            for e in schedule(load_scenario("shared-target"))
            if isinstance(e, SimDetection)
        }
        assert seen == {"F26E-001", "F26E-002", "F26E-003"}

    def test_crossing_columns_meet_at_the_junction(self) -> None:
        tracks = {t.id: t for t in target_tracks(load_scenario("crossing-columns"))}
        closest = min(
            distance_bearing(a[0], a[1], b[0], b[1])[0]
            for t in range(1500)
            if (a := tracks["EAST-1"].position(t / 10)) is not None
            and (b := tracks["NORTH-1"].position(t / 10)) is not None
        )
        assert closest < 50


class TestCli:
    """``fischer-gateway simulate --scenario``: usage errors exit 2 naming the problem."""

    def test_bad_scenario_exits_2_naming_file_line_and_key(self, tmp_path: Path) -> None:
        bad = tmp_path / "bad.yaml"
        bad.write_text(scenario_text().replace("class: tank", "class: helicopter"))
        done = simulate("--scenario", str(bad))
        assert done.returncode == 2
        assert f"{bad}:13 targets[0].class:" in done.stderr

    @pytest.mark.parametrize(
        ("extra", "option"),
        [
            (["--cot", "udp://127.0.0.1:9"], "--cot"),
            (["--scenario", "brigade", "--airframes", "2"], "--airframes"),
            (["--scenario", "brigade", "--cot", "127.0.0.1"], "--cot"),
        ],
    )
    def test_usage_errors_exit_2(self, extra: list[str], option: str) -> None:
        done = simulate(*extra)
        assert done.returncode == 2
        assert f"(command line) {option}:" in done.stderr
