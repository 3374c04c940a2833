"""A cue whose munition vanished is withdrawn at the battery, in the daemon as operators run it.

``fischer-gateway run --config FILE`` in a child process: two airframes on loopback UDP, the
``fusion`` processor (``lost_after_s`` short, so the test need not wait a minute),
``counter_uas`` with the scenario's battery and a ``gute2`` sink to a real HTTPS battery
(``GutePeer``: client certificate required, every body checked against the shipped JSON
Schema). ``fischer-gateway simulate --scenario loitering-munitions`` plays both Lancets to
their strike, where they vanish.

The battery must end with exactly one cue id per munition, each ending in one final revision
``withdrawn`` that says the track was lost and since when, with no effector recommended or
offered: no cue is left active for a munition the node no longer tracks.
"""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
from daemon_support import free_udp_port, running, wait_until
from gute_peer import GutePeer

from gateway.domain.geodesy import distance_bearing
from gateway.sim.scenario import load_scenario

pytestmark = pytest.mark.timeout(120)

SPEED = 8.0


def write_config(tmp_path: Path, peer: GutePeer, link: int) -> Path:
    battery = load_scenario("danger-close").batteries[0]  # the Boden battery both strike
    gute = peer.sink_options()
    config = tmp_path / "node.yaml"
    fleet = f"links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured, name: fleet}}]"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, {fleet}}}
  - {{id: F26E-002, sysid: 2, {fleet}}}
processors:
  # Played {SPEED:g} times faster: the priors scale; a munition silent 3 s (24 s of the
  # scenario) is lost, so the test does not wait the default minute.
  - {{name: fusion, type: fusion,
     options: {{speed_scale: {SPEED:g}, coast_after_s: 1, lost_after_s: 3, tick_s: 0.2}}}}
  - name: cuas
    type: counter_uas
    options:
      batteries:
        - id: {battery.id}
          lat_deg: {battery.lat_deg}
          lon_deg: {battery.lon_deg}
          effectors: {list(battery.effectors)}
sinks:
  - name: gute
    type: gute2
    options: {{url: '{gute["url"]}', ca_file: '{gute["ca_file"]}',
               cert_file: '{gute["cert_file"]}', key_file: '{gute["key_file"]}'}}
routes:
  - {{sinks: [gute], kinds: [handoff]}}
"""
    )
    return config


def by_cue(peer: GutePeer) -> dict[str, list[dict[str, Any]]]:
    """The documents the battery accepted, per cue id, in revision order."""
    cues: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for document in peer.accepted.values():
        cues[document["handoff_id"]].append(document)
    return {key: sorted(docs, key=lambda d: d["revision"]) for key, docs in cues.items()}


def test_each_munitions_cue_is_withdrawn_once_when_its_track_is_lost(tmp_path: Path) -> None:
    link = free_udp_port()
    with GutePeer(tmp_path / "pki").in_thread() as peer:
        config = write_config(tmp_path, peer, link)
        with running(config) as daemon:
            command = [sys.executable, "-m", "gateway", "simulate"]
            command += ["--scenario", "loitering-munitions", "--speed", str(SPEED)]
            command += ["--to", f"udp://127.0.0.1:{link}"]
            played = subprocess.run(command, capture_output=True, timeout=60, check=False)
            assert played.returncode == 0, played.stderr.decode(errors="replace")

            def every_cue_ended() -> bool:
                cues = by_cue(peer)
                return bool(cues) and all(d[-1]["status"] != "active" for d in cues.values())

            wait_until(every_cue_ended, 20.0, "every cue withdrawn or superseded")
            detail = next(
                p["detail"] for p in daemon.status()["processors"] if p["processor"] == "cuas"
            )
    cues = by_cue(peer)
    scenario = load_scenario("loitering-munitions")
    starts = {target.id: target.path[0] for target in scenario.targets}
    munition_of: dict[str, str] = {}
    for handoff_id, documents in cues.items():
        assert [d["revision"] for d in documents] == list(range(len(documents))), handoff_id
        where = documents[0]["track"]["position"]
        distances = {
            name: distance_bearing(where["lat_deg"], where["lon_deg"], p.lat_deg, p.lon_deg)[0]
            for name, p in starts.items()
        }
        munition_of[handoff_id] = min(distances, key=lambda name: distances[name])
    # Exactly one cue id per munition (revisions allowed), and none left active.
    assert sorted(munition_of.values()) == ["LM-1", "LM-2"], munition_of
    for handoff_id, documents in cues.items():
        *before, last = documents
        assert all(d["status"] == "active" for d in before), handoff_id
        assert last["status"] == "withdrawn", handoff_id
        assert last["revision"] >= 1
        assert last["idempotency_key"] == f"{handoff_id}-r{last['revision']}"
        assert last["note"].startswith(f"track {last['track']['track_id']} lost: no detection")
        assert last["track"]["last_seen"][:19] in last["note"]
        assert last["recommended_effector"] is None
        assert last["options"] == []
        assert last["superseded_by"] is None
        assert last["operator_authorisation_required"] is True
    assert detail["withdrawn"] == 2
    assert detail["handed_off"] == 2
