"""``fischer-gateway spool``: status, dead letters, show and re-queue beside a gateway."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path

import pytest

from gateway.cli import main
from gateway.events import Detection, Position, Sensor
from gateway.spool.store import Spool


def detection(n: int) -> Detection:
    return Detection(
        event_id=f"det-{n}",
        airframe="F26E-001",
        time=datetime(2026, 11, 23, tzinfo=UTC),
        sensor=Sensor.EO,
        object_class="tank",
        confidence=0.9,
        position=Position(lat_deg=65.8, lon_deg=21.7),
        sigma_h_m=8.0,
    )


AIRFRAME = """\
airframes:
  - {id: F26E-001, sysid: 1, links: [{uri: 'udp://127.0.0.1:14550', security: unsecured}]}
"""


@pytest.fixture
def node(tmp_path: Path) -> tuple[Path, Spool]:
    config = tmp_path / "node.yaml"
    config.write_text(f"spool: {{path: '{tmp_path / 'spool.db'}'}}\n" + AIRFRAME)
    owner = Spool(tmp_path / "spool.db")  # the running gateway holds it
    for n in range(3):
        seq = owner.append(detection(n), ("slb",))
        if n < 2:
            owner.dead_letter("slb", [seq], f"422 report {n} refused")  # type: ignore[list-item]
    return config, owner


def test_status_lists_and_shows_dead_letters_beside_the_gateway(
    node: tuple[Path, Spool], capsys: pytest.CaptureFixture[str]
) -> None:
    config, owner = node
    assert main(["spool", "status", "--config", str(config)]) == 0
    out = capsys.readouterr().out
    assert "sink slb: 1 events owed" in out
    assert "dead letters: 2" in out
    assert main(["spool", "dead-letters", "--config", str(config), "--json"]) == 0
    letters = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [(d["event_id"], d["reason"]) for d in letters] == [
        ("det-1", "422 report 1 refused"),
        ("det-0", "422 report 0 refused"),
    ]
    assert main(["spool", "show", "--config", str(config), str(letters[0]["id"])]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["reason"] == "422 report 1 refused"
    assert shown["event"]["event_id"] == "det-1"
    assert main(["spool", "show", "--config", str(config), "999"]) == 1
    owner.close()


def test_requeue_marks_and_the_gateway_moves_them_back(
    node: tuple[Path, Spool], capsys: pytest.CaptureFixture[str]
) -> None:
    config, owner = node
    assert main(["spool", "requeue", "--config", str(config), "--all", "--sink", "slb"]) == 0
    assert "re-queued 2" in capsys.readouterr().out
    assert owner.take_requeued() == 2
    owed = [row.event.event_id for row in owner.pending("slb")]
    assert owed == ["det-2", "det-0", "det-1"]
    assert main(["spool", "requeue", "--config", str(config)]) == 2  # neither ids nor --all
    owner.close()


def test_a_relative_path_that_is_not_here_says_where_it_looked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    config = tmp_path / "node.yaml"
    config.write_text("spool: {path: spool.db}\n" + AIRFRAME)
    monkeypatch.chdir(tmp_path)
    assert main(["spool", "status", "--config", str(config)]) == 1
    err = capsys.readouterr().err
    assert str(tmp_path / "spool.db") in err
    assert "working directory" in err
    assert not (tmp_path / "spool.db").exists()  # looking never creates a spool
