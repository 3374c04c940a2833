"""A third-party sink, processor and source, each with its own entry point, through ``run``.

``tests/plugins/fake_plugins`` is laid out as an installed distribution (a module and its
``.dist-info`` with ``entry_points.txt``); the daemon finds all three through the entry-point
groups once that directory is on its ``PYTHONPATH``, exactly as it would a pip-installed one.
Each passes its contract checker (``gateway.contract``), as its author would check it; and
with the distribution installed, the project's tests that loop over plugins see only ours.
"""

from __future__ import annotations

import importlib
import json
import os
import socket
from pathlib import Path
from types import ModuleType

import pytest
from daemon_support import Airframe, archive_events, free_udp_port, running, wait_until
from own_plugins import own_types

from gateway.c2.plugins import GROUP, PROCESSOR_GROUP, SOURCE_GROUP, available
from gateway.contract import ContractViolation, check_processor, check_sink, check_source
from gateway.events import BlueForce, Extension, Track
from gateway.fleet.dialect import CLASS_NAMES

PACKAGE = Path(__file__).resolve().parent / "fake_plugins"

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def installed(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """The fake distribution installed in this process (on ``sys.path``); its module."""
    monkeypatch.syspath_prepend(str(PACKAGE))
    return importlib.import_module("fake_plugins")


def test_each_passes_its_contract_checker(installed: ModuleType, tmp_path: Path) -> None:
    tally = tmp_path / "tally.txt"
    check_sink(installed.Tally, {"path": str(tally)})
    assert tally.read_text().splitlines() == ["detection c-det", "track c-trk", "blue_force c-bf"]
    source = check_source(installed.Ticker, {"interval_s": 0.01, "callsign": "BRAVO"})
    assert source.published
    assert all(isinstance(e, BlueForce) and e.callsign == "BRAVO" for e in source.published)
    processor = check_processor(installed.Doubler, {"prefix": "X"})
    track, doubled = processor.published
    assert isinstance(track, Track)
    assert track.detection_ids == ("c-det",)
    assert isinstance(doubled, Extension)
    assert doubled.type == "fake.doubled"
    assert doubled.data == {"detection_id": "c-det", "track_id": track.track_id, "count": 1}


def test_the_processor_checker_refuses_what_it_does_not_declare(installed: ModuleType) -> None:
    with pytest.raises(ContractViolation, match=r"'fake\.undeclared', which its extension_events"):
        check_processor(installed.Doubler, {"misbehave": True})

    with pytest.raises(ContractViolation, match="'Doubled' is not a type name"):
        check_processor(installed.Misdeclared, {})


def test_installed_third_party_plugins_are_not_enumerated_as_ours(installed: ModuleType) -> None:
    assert available()["tally"] == "fake-plugins"
    for group, theirs in ((GROUP, "tally"), (PROCESSOR_GROUP, "doubler"), (SOURCE_GROUP, "ticker")):
        ours = own_types(group)
        assert ours
        assert theirs not in ours
    assert {"jsonl", "memory"} <= set(own_types(GROUP))


def test_a_third_party_processor_and_source_plug_in_through_config(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(
        "PYTHONPATH", os.pathsep.join([str(PACKAGE), os.environ.get("PYTHONPATH", "")])
    )
    port = free_udp_port()
    archive = tmp_path / "archive.jsonl"
    tally = tmp_path / "tally.txt"
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
airframes:
  - {{id: OPEN, sysid: 3, links: [{{uri: 'udp://127.0.0.1:{port}', security: unsecured}}]}}
sources:
  - {{name: tick, type: ticker, interval_s: 0.1, callsign: ALPHA, crash_every: 5}}
processors:
  - {{name: twin, type: doubler, options: {{prefix: TW, misbehave: true}}}}
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
  - {{name: counted, type: tally, options: {{path: '{tally}'}}}}
routes:
  - {{sinks: [archive]}}
  - {{kinds: [track, blue_force], sinks: [counted]}}
"""
    )
    plane = Airframe(3)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender, running(config) as daemon:
        for _ in range(3):
            sender.sendto(plane.detection(), ("127.0.0.1", port))

        def kinds() -> set[str]:
            return {str(e.get("kind")) for e in archive_events(archive)}

        wait_until(
            lambda: {"detection", "track", "blue_force", "extension"} <= kinds(), 10, "all four"
        )
        status = daemon.status()
        (processor,) = status["processors"]
        assert processor["processor"] == "twin"
        assert processor["state"] == "running"
        assert processor["events_in"] >= 3
        assert processor["events_out"] >= 3
        assert {s["source"] for s in status["sources"]} == {"tick"}
        # The ticker raises every 5 reports: restarted, never the end of the daemon.
        wait_until(lambda: daemon.status()["sources"][0]["restarts"] >= 1, 10, "a restart")
        assert daemon.get("/readyz")[0] == 200
        assert daemon.events("source_failed")
        assert daemon.metric("fg_processor_events_total", processor="twin", direction="out") >= 3
        # Its undeclared type and its invalid data were refused, counted under its name.
        for reason in ("undeclared", "invalid"):
            wait_until(
                lambda r=reason: (
                    daemon.metric(  # type: ignore[misc]
                        "fg_extension_refused_total", publisher="twin", reason=r
                    )
                    >= 3
                ),
                10,
                f"three refused as {reason}",
            )
        assert daemon.status()["processors"][0]["detail"]["refused"] == 6
        assert {e["reason"] for e in daemon.events("extension_refused")} == {
            "undeclared",
            "invalid",
        }
        assert all(e["processor"] == "twin" for e in daemon.events("extension_refused"))
    tracks = [e for e in archive_events(archive) if e["kind"] == "track"]
    expected = f"TW-OPEN-{CLASS_NAMES[1]}"  # the daemon_support detection's class_id
    assert {t["track_id"] for t in tracks} == {expected}
    assert len(tracks) == 3
    # Its own event type, archived whole by jsonl; nothing it was refused got there.
    extensions = [e for e in archive_events(archive) if e["kind"] == "extension"]
    assert len(extensions) == 3
    assert {e["type"] for e in extensions} == {"fake.doubled"}
    assert {e["publisher"] for e in extensions} == {"twin"}
    assert {e["airframe"] for e in extensions} == {"OPEN"}
    assert sorted(e["data"]["count"] for e in extensions) == [1, 2, 3]
    assert {e["data"]["track_id"] for e in extensions} == {expected}
    ticks = [e for e in archive_events(archive) if e["kind"] == "blue_force"]
    assert all(t["callsign"] == "ALPHA" for t in ticks)
    assert json.dumps(ticks[0])  # archived whole
    # The third-party sink got what its route sends it, from the third-party plugins.
    counted = [line.split() for line in tally.read_text().splitlines()]
    assert {kind for kind, _ in counted} == {"track", "blue_force"}
    assert {event_id for kind, event_id in counted if kind == "track"} == {
        t["event_id"] for t in tracks
    }


def test_a_bad_plugin_option_is_a_config_error_with_its_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": str(PACKAGE)}
    config = tmp_path / "c.yaml"
    config.write_text(
        "airframes:\n  - {id: A, sysid: 1, links: [{uri: 'udp://127.0.0.1:14550', "
        "security: unsecured}]}\n"
        "sources:\n  - {name: tick, type: ticker, intervl_s: 1}\n"
        "processors:\n  - {name: twin, type: doubler, options: {prefx: X}}\n"
        "  - {name: other, type: nosuch}\n"
        "  - {name: bad, type: misdeclared}\n"
    )
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", str(config)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env=env,
    )
    assert result.returncode == 2
    assert (
        f"{config}:4 sources[0].intervl_s: unknown key 'intervl_s'; did you mean 'interval_s'?"
        in result.stderr
    )
    assert (
        "processors[0].options.prefx: unknown key 'prefx'; did you mean 'prefix'?" in result.stderr
    )
    assert "processors[1].type: unknown processor type 'nosuch'" in result.stderr
    assert (
        "processors[2].type: processor type 'misdeclared' from fake-plugins 0.1: "
        "extension_events: 'Doubled' is not a type name" in result.stderr
    )
