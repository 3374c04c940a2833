"""Detection re-sends the way operators run them: ``fischer-gateway simulate`` as a process.

First against a pymavlink ground station that acknowledges (``tests/ack_peer.py``), in the
tunnel with day keys made by ``fischer-gateway keys derive``: the link is cut for a while and
some acknowledgements are decoys, and the command must end with every detection delivered
and its summary saying nothing is left unacknowledged. Then against ``fischer-gateway run``
with a spool file: every detection acknowledged and archived once, and through a restart of
the gateway in the middle of the run, every detection still acknowledged and archived.
Loopback only.
"""

from __future__ import annotations

import hashlib
import re
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from types import ModuleType

import anyio
import pytest
from ack_peer import AckPeer, Answer, Arrival, generate_dialect

from tests.daemon_support import (
    Daemon,
    archive_events,
    free_udp_port,
    running,
    wait_until,
    write_key,
)

pytestmark = pytest.mark.timeout(90)

MASTER = hashlib.sha256(b"detection-ack e2e master").digest()
GATEWAY = [sys.executable, "-m", "gateway"]
SUMMARY = re.compile(
    r"^(?P<name>.+) \(sysid (?P<sysid>\d+)\): detections sent (?P<sent>\d+), re-sent "
    r"(?P<resent>\d+), acknowledged (?P<acknowledged>\d+), dropped (?P<dropped>\d+), "
    r"unacknowledged (?P<unacknowledged>\d+)(?: \(re-send off\))?; sends refused "
    r"(?P<refused>\d+), uplink rejected (?P<rejected>\d+)$"
)
#: One airframe watching a tank column at 5 Hz for 24 s of sim time.
SCENARIO = """\
name: restart
duration_s: 24
seed: 3
airframes:
  - id: F26E-001
    sysid: 1
    orbit: {centre_lat_deg: 65.84, centre_lon_deg: 21.70, radius_m: 500, alt_msl_m: 600,
            speed_mps: 25}
    sensors:
      - {sensor: eo, range_m: 8000, confidence: 0.8, sigma_h_m: 10, rate_hz: 5}
targets:
  - id: COL
    class: tank
    subtype: T-72B3
    speed_mps: 5
    path:
      - {lat_deg: 65.85, lon_deg: 21.70, alt_msl_m: 60}
      - {lat_deg: 65.86, lon_deg: 21.71, alt_msl_m: 60}
"""


def summaries(stdout: bytes) -> dict[int, dict[str, int]]:
    """The per-airframe summary lines of ``simulate``, by sysid."""
    out = {}
    for line in stdout.decode().splitlines():
        match = SUMMARY.match(line)
        if match is not None:
            values = {k: int(v) for k, v in match.groupdict().items() if k != "name"}
            out[values["sysid"]] = values
    return out


@pytest.fixture(scope="module")
def dialect(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    return generate_dialect(tmp_path_factory.mktemp("mavgen"))


def decoy_then_ack(arrival: Arrival, copy: int) -> Answer:
    """Every third detection's first acknowledgement is a decoy (unsealed): ignored."""
    return "decoy" if arrival.detection_id % 3 == 0 and copy == 1 else "ack"


@pytest.mark.anyio
async def test_simulate_resends_in_the_tunnel_until_every_detection_is_acknowledged(
    tmp_path: Path, dialect: ModuleType
) -> None:
    master = write_key(tmp_path / "master.key", MASTER)
    ids = ["F26E-001", "F26E-002"]
    today = datetime.now(UTC).date().isoformat()
    for airframe in ids:
        derive = [*GATEWAY, "keys", "derive", "--master", str(master), "--airframe", airframe]
        derive += ["--from", today, "--days", "2", "--out", str(tmp_path / "keys")]
        await anyio.run_process(derive)
    with anyio.fail_after(60):
        async with (
            AckPeer.bound(
                dialect,
                answer=decoy_then_ack,
                # The link drops everything after the 4th detection until 8 are lost.
                cut=lambda p: len(p.arrivals) >= 4 and len(p.lost) < 8,
                master=MASTER,
                airframe_ids={1: ids[0], 2: ids[1]},
            ) as peer,
            anyio.create_task_group() as tg,
        ):
            tg.start_soon(peer.serve)
            command = [*GATEWAY, "simulate", "--to", f"udp://127.0.0.1:{peer.port}"]
            command += ["--airframes", "2", "--duration", "60", "--speed", "30"]
            command += ["--key-dir", str(tmp_path / "keys")]
            command += ["--airframe-id", ids[0], "--airframe-id", ids[1]]
            command += ["--resend-first", "0.1", "--resend-max", "0.3", "--linger", "10"]
            done = await anyio.run_process(command, check=False)
            tg.cancel_scope.cancel()
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    lines = summaries(done.stdout)
    assert sorted(lines) == [1, 2]
    for sysid, line in lines.items():
        sent = line["sent"]
        assert sent == 13  # every 5 s of sim time over 60 s, both ends included
        assert (line["acknowledged"], line["unacknowledged"], line["dropped"]) == (sent, 0, 0)
        assert line["rejected"] == len([i for i in range(1, sent + 1) if i % 3 == 0])
        delivered = {a.detection_id for a in peer.arrivals if a.sysid == sysid}
        assert delivered == set(range(1, sent + 1))
    assert len(peer.lost) == 8
    assert set(peer.lost) <= peer.identities()
    assert sum(line["resent"] for line in lines.values()) >= 8
    assert peer.rejected == 0  # everything the airframes sent opened


def write_node(tmp_path: Path, link_port: int) -> tuple[Path, Path]:
    archive = tmp_path / "archive.jsonl"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
spool: {{path: '{tmp_path / "spool.db"}'}}
airframes:
  - id: F26E-001
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{link_port}', security: unsecured, name: fleet}}]
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive], kinds: [detection]}}
"""
    )
    return config, archive


def archived_detections(archive: Path) -> list[int]:
    """The detection_id of every detection line in the archive (event ids end id-time_usec)."""
    return [
        int(e["event_id"].rsplit("-", 2)[1])
        for e in archive_events(archive)
        if e["kind"] == "detection"
    ]


def test_the_gateway_acknowledges_every_detection_and_archives_each_once(
    tmp_path: Path,
) -> None:
    link = free_udp_port()
    config, archive = write_node(tmp_path, link)
    scenario = tmp_path / "restart.yaml"
    scenario.write_text(SCENARIO.replace("duration_s: 24", "duration_s: 8"))
    with running(config) as daemon:
        command = [*GATEWAY, "simulate", "--scenario", str(scenario)]
        command += ["--to", f"udp://127.0.0.1:{link}", "--speed", "4"]
        played = subprocess.run(command, capture_output=True, timeout=30, check=False)
        assert played.returncode == 0, played.stderr.decode(errors="replace")
        (line,) = summaries(played.stdout).values()
        wait_until(lambda: len(archived_detections(archive)) >= line["sent"], 10, "archive")
        acked = daemon.metric(
            "fg_detections_acknowledged_total", airframe="F26E-001", result="held"
        )
    assert line["sent"] == 41  # 5 Hz over 8 s of sim time, both ends included
    assert (line["acknowledged"], line["unacknowledged"], line["dropped"]) == (41, 0, 0)
    assert line["resent"] == 0  # nothing was lost on loopback, so nothing was sent twice
    assert acked == 41
    assert sorted(archived_detections(archive)) == list(range(1, 42))


def test_a_gateway_restarted_mid_run_ends_with_every_detection_acknowledged_and_archived(
    tmp_path: Path,
) -> None:
    link = free_udp_port()
    config, archive = write_node(tmp_path, link)
    scenario = tmp_path / "restart.yaml"
    scenario.write_text(SCENARIO)
    command = [*GATEWAY, "simulate", "--scenario", str(scenario), "--to"]
    command += [f"udp://127.0.0.1:{link}", "--speed", "4"]
    command += ["--resend-first", "0.2", "--resend-max", "0.5", "--linger", "10"]
    first = Daemon(config)
    try:
        simulator = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        time.sleep(1.0)  # a second of the run reaches the first gateway
        assert first.stop() == 0
        with running(config):  # the gateway's restart: about a second without a listener
            stdout, stderr = simulator.communicate(timeout=30)
            assert simulator.returncode == 0, stderr.decode(errors="replace")
            (line,) = summaries(stdout).values()
            expected = set(range(1, line["sent"] + 1))
            wait_until(lambda: set(archived_detections(archive)) >= expected, 10, "archive")
    finally:
        first.stop()
    assert line["sent"] == 121  # 5 Hz over 24 s of sim time
    assert line["refused"] > 0  # the airframe did send into the restart
    assert line["resent"] > 0
    assert (line["acknowledged"], line["unacknowledged"], line["dropped"]) == (121, 0, 0)
    assert set(archived_detections(archive)) == expected
