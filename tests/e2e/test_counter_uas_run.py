"""Detections to a GUTE II cue in the daemon as operators run it: the brigade scenario.

``fischer-gateway run --config FILE`` in a child process: two airframes on loopback UDP, the
CoT source for the platoons, processors ``fusion`` and ``counter_uas`` (the scenario's battery)
and a ``gute2`` sink to a real HTTPS battery (``GutePeer``: client certificate required, every
body checked against the shipped JSON Schema) whose first three POSTs fail with 503.
``fischer-gateway simulate --scenario brigade`` plays the operation at six times real speed.

The battery must end with exactly one handoff per cued track (every revision of it accepted
once, whatever was retried), both Lancets cued, no tank cued, and LM-1's cue revised to
"deconfliction not clear" with no effector recommended while it passes VIDAR 1.
"""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
from daemon_support import archive_events, free_udp_port, running, wait_until
from gute_peer import GutePeer

from gateway.domain.geodesy import distance_bearing
from gateway.sim.scenario import load_scenario

pytestmark = pytest.mark.timeout(120)

SPEED = 6.0


def write_config(tmp_path: Path, peer: GutePeer, link: int, cot: int) -> tuple[Path, Path]:
    battery = load_scenario("brigade").batteries[0]
    archive = tmp_path / "archive.jsonl"
    gute = peer.sink_options()
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 3}}
health: {{port: 0}}
airframes:
  - {{id: F26E-001, sysid: 1, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}
  - {{id: F26E-002, sysid: 2, links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured,
     name: fleet}}]}}
sources:
  - {{name: atak, uri: 'udp://127.0.0.1:{cot}'}}
processors:
  - {{name: fusion, type: fusion, options: {{max_speed_mps: 400}}}}
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
    retry_initial_s: 0.2
    retry_max_s: 0.5
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [gute], kinds: [handoff]}}
  - {{sinks: [archive]}}
"""
    )
    return config, archive


@pytest.fixture(scope="module")
def brigade(tmp_path_factory: pytest.TempPathFactory) -> tuple[GutePeer, list[dict[str, Any]]]:
    tmp_path = tmp_path_factory.mktemp("brigade")
    link, cot = free_udp_port(), free_udp_port()
    with GutePeer(tmp_path / "pki", fail_first=3).in_thread() as peer:
        config, archive = write_config(tmp_path, peer, link, cot)
        with running(config):
            command = [sys.executable, "-m", "gateway", "simulate", "--scenario", "brigade"]
            command += ["--to", f"udp://127.0.0.1:{link}", "--cot", f"udp://127.0.0.1:{cot}"]
            command += ["--speed", str(SPEED)]
            played = subprocess.run(command, capture_output=True, timeout=60, check=False)
            assert played.returncode == 0, played.stderr.decode(errors="replace")

            def all_cues_delivered() -> bool:
                published = {
                    e["event_id"] for e in archive_events(archive) if e["kind"] == "handoff"
                }
                return bool(published) and published <= set(peer.accepted)

            wait_until(all_cues_delivered, 15.0, "every published cue accepted by the battery")
        return peer, archive_events(archive)


def cues_by_track(peer: GutePeer) -> dict[str, list[dict[str, Any]]]:
    by_track: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for document in peer.accepted.values():
        by_track[document["track"]["track_id"]].append(document)
    return by_track


def test_the_battery_gets_exactly_one_handoff_per_track_despite_failed_posts(
    brigade: tuple[GutePeer, list[dict[str, Any]]],
) -> None:
    peer, _ = brigade
    statuses = [request.status for request in peer.posts]
    assert statuses[:3] == [503, 503, 503]  # the retries came after these
    assert 400 not in statuses  # every body passed the schema and named its key
    assert peer.handshake_failures == []
    for track_id, documents in cues_by_track(peer).items():
        assert len({d["handoff_id"] for d in documents}) == 1, track_id
        revisions = sorted(d["revision"] for d in documents)
        assert revisions == list(range(len(documents))), track_id  # each revision once
        for document in documents:
            assert document["operator_authorisation_required"] is True
            assert document["track"]["object_class"] == "loitering_munition"
            assert document["battery"]["id"] == "GUTE-1"


def test_both_lancets_are_cued_and_the_tanks_are_not(
    brigade: tuple[GutePeer, list[dict[str, Any]]],
) -> None:
    peer, events = brigade
    tracks = [e for e in events if e["kind"] == "track"]
    assert {t["object_class"] for t in tracks} >= {"loitering_munition", "tank"}
    munitions = {
        t["track_id"]
        for t in tracks
        if t["object_class"] == "loitering_munition" and t["confidence"] >= 0.95 - 1e-9
    }
    cued = set(cues_by_track(peer))
    assert cued <= munitions
    scenario = load_scenario("brigade")
    starts = {
        target.id: target.path[0] for target in scenario.targets if target.id in ("LM-1", "LM-2")
    }
    near: set[str] = set()
    for documents in cues_by_track(peer).values():
        first = min(documents, key=lambda d: d["revision"])
        where = first["track"]["position"]
        distances = {
            name: distance_bearing(where["lat_deg"], where["lon_deg"], p.lat_deg, p.lon_deg)[0]
            for name, p in starts.items()
        }
        near.add(min(distances, key=lambda name: distances[name]))
    assert near == {"LM-1", "LM-2"}


def test_the_lancet_passing_a_platoon_is_recued_not_clear_with_no_effector(
    brigade: tuple[GutePeer, list[dict[str, Any]]],
) -> None:
    peer, _ = brigade
    held = [
        d
        for documents in cues_by_track(peer).values()
        for d in documents
        if not d["deconfliction"]["clear"]
    ]
    assert held, "no cue was ever not clear"
    for document in held:
        assert document["recommended_effector"] is None
        assert document["deconfliction"]["nearest_blue_callsign"] == "VIDAR 1"
        # The platoons report over CoT: their callsigns are marked for what they are.
        assert document["deconfliction"]["nearest_blue_callsign_provenance"] == (
            "unauthenticated CoT callsign"
        )
        assert document["deconfliction"]["nearest_blue_source"] == "atak"
        assert document["revision"] >= 1  # first cued clear, far out; revised as it closed in
        inside = [o for o in document["options"] if not o["deconfliction_clear"]]
        assert inside
        margin = document["deconfliction"]["nearest_blue_m"] - document["track"]["cep90_m"]
        assert all(margin <= o["danger_close_m"] for o in inside)
