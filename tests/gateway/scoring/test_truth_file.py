"""The truth file: what ``gateway.sim.truth`` writes, read back, and refused when wrong."""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import pytest

from gateway.domain.geodesy import distance_bearing
from gateway.errors import ScoreInputError
from gateway.scoring.files import read_archive, read_truth
from gateway.scoring.model import Plane
from gateway.sim.scenario import load_scenario
from gateway.sim.schedule import target_tracks
from gateway.sim.truth import TRUTH_FORMAT, write_truth

START = 1_800_000_000.0
GATEWAY = [sys.executable, "-m", "gateway"]


def lines_of(name: str, speed: float = 1.0) -> list[dict[str, object]]:
    out = io.StringIO()
    write_truth(out, load_scenario(name), START, speed=speed)
    return [json.loads(line) for line in out.getvalue().splitlines()]


class TestWrite:
    """One header, then one line per target per second, as the simulator moves them."""

    def test_header_names_the_run(self) -> None:
        header = lines_of("t72-column", speed=4.0)[0]
        assert header == {
            "format": TRUTH_FORMAT,
            "scenario": "t72-column",
            "start_utc": "2027-01-15T08:00:00Z",
            "speed": 4.0,
            "step_s": 1.0,
            "duration_s": 90.0,
            "targets": ["COL-1", "COL-2", "COL-3", "COL-4"],
        }

    def test_positions_are_the_simulators_and_utc_follows_the_speed(self) -> None:
        records = lines_of("t72-column", speed=4.0)[1:]
        tracks = {t.id: t for t in target_tracks(load_scenario("t72-column"))}
        assert {r["target"] for r in records} == set(tracks)
        for r in records:
            t_s = r["t_s"]
            assert isinstance(t_s, float)
            where = tracks[str(r["target"])].position(t_s)
            assert where is not None
            assert (r["lat_deg"], r["lon_deg"], r["alt_msl_m"]) == where
            utc = datetime.fromisoformat(str(r["utc"])).timestamp()
            assert utc == pytest.approx(START + t_s / 4.0, abs=1e-6)
            assert (r["object_class"], r["subtype"], r["affiliation"]) == (
                "tank",
                "T-72B3",
                "hostile",
            )

    def test_velocity_is_along_the_road_at_10_mps(self) -> None:
        records = [r for r in lines_of("t72-column")[1:] if r["target"] == "COL-1"]
        first, second = records[10], records[11]
        north, east = float(first["north_mps"]), float(first["east_mps"])  # type: ignore[arg-type]
        assert math.hypot(north, east) == pytest.approx(10.0)
        moved, bearing = distance_bearing(
            float(first["lat_deg"]),  # type: ignore[arg-type]
            float(first["lon_deg"]),  # type: ignore[arg-type]
            float(second["lat_deg"]),  # type: ignore[arg-type]
            float(second["lon_deg"]),  # type: ignore[arg-type]
        )
        assert moved == pytest.approx(10.0, abs=0.01)
        assert math.degrees(math.atan2(east, north)) % 360 == pytest.approx(bearing, abs=0.1)

    def test_a_parked_vehicle_has_no_velocity_and_a_struck_munition_no_line(self) -> None:
        parked = lines_of("parked-vehicles")[1:]
        assert {(r["north_mps"], r["east_mps"]) for r in parked} == {(0.0, 0.0)}
        swarm = lines_of("swarm")[1:]
        assert max(float(r["t_s"]) for r in swarm) < 100  # type: ignore[arg-type]


class TestRead:
    """``read_truth`` gives one frame per second; bad files name their line."""

    def test_round_trip(self, tmp_path: Path) -> None:
        path = tmp_path / "truth.jsonl"
        with path.open("w") as f:
            write_truth(f, load_scenario("t72-column"), START, speed=2.0)
        truth = read_truth(path)
        assert (truth.scenario, truth.speed, len(truth.frames)) == ("t72-column", 2.0, 91)
        assert truth.frames[20].unix_s == pytest.approx(START + 10.0)
        assert [t.target for t in truth.frames[20].targets] == ["COL-1", "COL-2", "COL-3", "COL-4"]
        lead = truth.frames[0].targets[0]
        assert (lead.x, lead.y) == pytest.approx((0.0, 0.0))

    @pytest.mark.parametrize(
        ("edit", "line", "message"),
        [
            (lambda ls: ["{not json", *ls[1:]], 1, "not a JSON line"),
            (lambda ls: ['{"format": "other/1"}', *ls[1:]], 1, "expected a header with format"),
            (lambda ls: [*ls[:3], ls[3].replace('"t_s": 2.0', '"t_s": 2.5')], 4, "not a step"),
            (lambda ls: [*ls[:2], ls[2].replace('"lat_deg": ', '"lat_deg": "x", "y": ')], 3, "lat"),
            (lambda ls: [*ls[:2], "[1, 2]"], 3, "expected a JSON object"),
        ],
    )
    def test_a_bad_line_is_named(
        self, tmp_path: Path, edit: object, line: int, message: str
    ) -> None:
        out = io.StringIO()
        write_truth(out, load_scenario("danger-close"), START)
        lines = out.getvalue().splitlines()
        path = tmp_path / "truth.jsonl"
        path.write_text("\n".join(edit(lines)) + "\n")  # type: ignore[operator]
        with pytest.raises(ScoreInputError, match=message) as caught:
            read_truth(path)
        assert str(caught.value).startswith(f"{path}:{line}: ")

    def test_a_missing_file_is_named(self, tmp_path: Path) -> None:
        with pytest.raises(ScoreInputError, match="No such file"):
            read_truth(tmp_path / "nope.jsonl")


def test_archive_lines_that_are_not_events_are_counted_not_fatal(tmp_path: Path) -> None:
    archive = tmp_path / "archive.jsonl"
    good = {
        "kind": "track",
        "event_id": "e1",
        "track_id": "T-1",
        "time": "2027-01-15T08:00:00Z",
        "object_class": "tank",
        "confidence": 0.8,
        "position": {"lat_deg": 65.8, "lon_deg": 21.7},
        "cep50_m": 10.0,
        "cep90_m": 18.0,
        "first_seen": "2027-01-15T08:00:00Z",
        "last_seen": "2027-01-15T08:00:00Z",
    }
    bad = {**good, "position": {"lat_deg": 123.0, "lon_deg": 0.0}}
    archive.write_text(
        json.dumps({"kind": "telemetry"}) + "\n"
        + json.dumps(bad, separators=(",", ":")) + "\n"
        + json.dumps(good, separators=(",", ":")) + "\n"
        + '{"kind":"track", cut mid-li'
    )  # fmt: skip
    tracks = read_archive([archive], Plane(65.8, 21.7))
    assert list(tracks.reports) == ["T-1"]
    assert (tracks.skipped_lines, tracks.first_skipped_line) == (2, 2)


class TestCli:
    """``fischer-gateway score`` and ``simulate --truth`` as a user runs them."""

    def test_score_with_a_bad_truth_exits_2_naming_the_line(self, tmp_path: Path) -> None:
        truth = tmp_path / "truth.jsonl"
        truth.write_text('{"format": "fischer-truth/1"}\n')
        archive = tmp_path / "archive.jsonl"
        archive.write_text("")
        done = subprocess.run(
            [*GATEWAY, "score", "--truth", str(truth), "--tracks", str(archive)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert done.returncode == 2
        assert f"{truth}:1: " in done.stderr

    def test_truth_without_a_scenario_is_a_usage_error(self, tmp_path: Path) -> None:
        done = subprocess.run(
            [*GATEWAY, "simulate", "--to", "udp://127.0.0.1:9", "--truth", str(tmp_path / "t")],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert done.returncode == 2
        assert "(command line) --truth:" in done.stderr
