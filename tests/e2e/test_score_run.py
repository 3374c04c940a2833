"""Ground truth and the scorer as a user runs them: ``simulate --truth`` into ``run``, then
``fischer-gateway score`` on the daemon's archive.

The daemon runs the ``fusion`` and ``counter_uas`` processors and a jsonl archive on
loopback; the simulator plays the first 30 s of ``danger-close`` (one Lancet-3, EO and IR)
at four times real speed and writes its truth. The scorer must find the one munition tracked
from the archive with a position error of the sensors' order (so the truth's UTC times line
up with the gateway's), speeds compared in scenario units, and the munition's cue.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
from datetime import datetime, timedelta
from pathlib import Path

import pytest
from daemon_support import archive_events, free_udp_port, running, wait_until

pytestmark = pytest.mark.timeout(120)

GATEWAY = [sys.executable, "-m", "gateway"]


def write_node(tmp_path: Path, port: int) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    link = f"links: [{{uri: 'udp://127.0.0.1:{port}', security: unsecured, name: fleet}}]"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, {link}}}
  - {{id: F26E-002, sysid: 2, {link}}}
processors:
  # --speed 4: a 30 m/s Lancet appears at 120 m/s; the tracker's priors scale with it.
  - {{name: fusion, type: fusion, options: {{speed_scale: 4}}}}
  - name: cuas
    type: counter_uas
    options:
      batteries:
        - {{id: GUTE-1, lat_deg: 65.8235, lon_deg: 21.6955, alt_msl_m: 40,
           effectors: [TRIDON_MK2_40MM, TRACKFIRE_30MM]}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{kinds: [track, handoff], sinks: [archive]}}
"""
    )
    return config, archive


def test_simulate_truth_then_score_the_archive(tmp_path: Path) -> None:
    port = free_udp_port()
    config, archive = write_node(tmp_path, port)
    truth = tmp_path / "truth.jsonl"
    with running(config):
        play = ["simulate", "--scenario", "danger-close", "--to", f"udp://127.0.0.1:{port}"]
        play += ["--duration", "30", "--speed", "4", "--truth", str(truth)]
        simulate = subprocess.run([*GATEWAY, *play], capture_output=True, timeout=60, check=False)
        assert simulate.returncode == 0, simulate.stderr.decode(errors="replace")

        last = json.loads(truth.read_text().split("\n")[-2])
        end = datetime.fromisoformat(last["utc"]) - timedelta(seconds=1)

        def late_track() -> bool:
            times = [
                datetime.fromisoformat(e["time"])
                for e in archive_events(archive)
                if e["kind"] == "track"
            ]
            return bool(times) and max(times) >= end

        wait_until(late_track, 15.0, "a track of the run's last second in the archive")
    header = json.loads(truth.read_text().split("\n")[0])
    assert (header["scenario"], header["speed"], header["duration_s"]) == (
        "danger-close",
        4.0,
        30.0,
    )
    scored = subprocess.run(
        [*GATEWAY, "score", "--truth", str(truth), "--tracks", str(archive), "--json"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert scored.returncode == 0, scored.stderr
    result = json.loads(scored.stdout)
    assert (result["scenario"], result["seconds"], result["targets"]) == ("danger-close", 31, 1)
    assert result["targets_tracked"] == 1
    assert result["matched_pairs"] >= 25
    # σ 12 and 18 m: the clocks line up. The median second, not the RMSE: until the track's
    # velocity is known (about 3 updates) it is shown where it was last seen, and at four
    # times real speed a Lancet is then up to 90 m past it.
    assert statistics.median(result["gospa_per_second"]) < 30
    assert result["true_speed_median"] == pytest.approx(30.0)
    assert result["speed_error_median"] < 15  # in scenario m/s, not the 120 m/s seen
    assert result["cues_per_munition"]["LM-1"] >= 1
    assert result["unmatched_cues"] == 0
    text = subprocess.run(
        [*GATEWAY, "score", "--truth", str(truth), "--tracks", str(archive)],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout
    assert text.startswith("scenario danger-close: 31 s, 1 targets (1 tracked)")
