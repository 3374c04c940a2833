"""The command line as operators use it, always through ``python -m gateway``."""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import pytest

from gateway.ops.gcsetup import GEN0_THRESHOLD
from gateway.ops.version import package_version
from gateway.sim.airframe import SimulatedAirframe

ROOT = Path(__file__).resolve().parents[2]
T0_US = 1_763_800_000_000_000  # 2025-11-22T08:26:40Z


def cli(
    *args: str, env: dict[str, str] | None = None, **kwargs: Any
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env=env,
        **kwargs,
    )


def records(text: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


def write_tlog(path: Path, count: int, gap_s: float) -> Path:
    frame = SimulatedAirframe(1).frames_at(0.0)[0]
    stamps = [T0_US + round(i * gap_s * 1e6) for i in range(count)]
    path.write_bytes(b"".join(struct.pack(">Q", ts) + frame for ts in stamps))
    return path


def test_version_is_the_installed_distributions() -> None:
    result = cli("--version")
    assert result.returncode == 0
    assert result.stdout.strip() == f"fischer-gateway {package_version()}"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["replay", "x.tlog", "--to", "udp://127.0.0.1:9", "--speed", "0"],
            "--speed: expected a positive",
        ),
        (
            ["replay", "x.tlog", "--to", "udp://127.0.0.1:9", "--speed", "nan"],
            "--speed: expected a positive",
        ),
        (["simulate", "--to", "udp://127.0.0.1:9", "--airframes", "300"], "expected 1..255"),
        (["simulate", "--to", "udp://127.0.0.1:9", "--airframes", "0"], "8-bit MAVLink system id"),
        (["simulate", "--to", "udp://127.0.0.1:9", "--duration", "-1"], "--duration: expected"),
        (["simulate", "--to", "udp://127.0.0.1:9", "--resend-rate", "0"], "--resend-rate: exp"),
        (["simulate", "--to", "udp://127.0.0.1:9", "--linger", "-1"], "--linger: expected"),
        (
            ["simulate", "--to", "udp://127.0.0.1:9", "--resend-first", "2", "--resend-max", "1"],
            "--resend-max: expected at least --resend-first (2), got 1",
        ),
        (["demo", "--udp-port", "70000"], "--udp-port: expected a port 0..65535"),
    ],
)
def test_impossible_arguments_are_usage_errors(args: list[str], message: str) -> None:
    result = cli(*args)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr


class TestReplay:
    """replay says how far it got, and says so when nothing listens."""

    def test_progress_is_logged_while_it_runs(self, tmp_path: Path) -> None:
        path = write_tlog(tmp_path / "a.tlog", count=9, gap_s=0.1)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as listener:
            listener.bind(("127.0.0.1", 0))
            port = listener.getsockname()[1]
            result = cli(
                "replay", str(path), "--to", f"udp://127.0.0.1:{port}", "--progress-s", "0.2"
            )
        assert result.returncode == 0, result.stderr
        logged = records(result.stderr)
        progress = [r for r in logged if r["event"] == "replay_progress"]
        assert len(progress) >= 2
        sent = [r["frames_sent"] for r in progress]
        assert sent == sorted(sent)
        assert 0 < sent[0] < 9
        assert progress[0]["log_time"].startswith("2025-11-22T08:26:40")
        assert 0 < progress[-1]["log_position_s"] <= 0.8
        assert logged[-1]["event"] == "replay_finished"
        assert logged[-1]["frames"] == 9

    def test_a_port_nobody_listens_on_is_reported_not_finished(self, tmp_path: Path) -> None:
        """Loopback answers a datagram to a closed port with ICMP port-unreachable."""
        path = write_tlog(tmp_path / "a.tlog", count=20, gap_s=0.01)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as closed:
            closed.bind(("127.0.0.1", 0))
            port = closed.getsockname()[1]
        result = cli("replay", str(path), "--to", f"udp://127.0.0.1:{port}", "--fast")
        assert result.returncode == 1
        events = [r["event"] for r in records(result.stderr)]
        assert "replay_refused" in events
        assert events[-1] == "replay_unheard"
        assert "replay_finished" not in events
        assert records(result.stderr)[-1]["refused"] > 0


def udp_config(tmp_path: Path, port: int, node: str = "n1") -> Path:
    path = tmp_path / "c.yaml"
    path.write_text(
        f"gateway: {{node_id: {node}, shutdown_deadline_s: 1}}\nhealth: {{port: 0}}\n"
        "airframes:\n  - {id: A, sysid: 1, links: "
        f"[{{uri: 'udp://127.0.0.1:{port}', security: unsecured}}]}}\n"
    )
    return path


class TestRunFailures:
    """A start-up failure keeps its reason, and journald gets its priority."""

    def test_a_udp_port_in_use_keeps_errno_and_strerror_under_uvloop(self, tmp_path: Path) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
            busy.bind(("127.0.0.1", 0))
            config = udp_config(tmp_path, busy.getsockname()[1])
            result = cli("run", "--config", str(config))
        assert result.returncode == 1
        (failed,) = [r for r in records(result.stderr) if r["event"] == "gateway_failed"]
        assert (failed["errno"], failed["strerror"]) == (98, "Address already in use")
        assert failed["error"].endswith("Address already in use")  # the message itself too

    def test_under_journald_lines_carry_their_priority(self, tmp_path: Path) -> None:
        log_path = tmp_path / "journal.txt"
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
            busy.bind(("127.0.0.1", 0))
            config = udp_config(tmp_path, busy.getsockname()[1])
            with log_path.open("w") as journal:
                st = os.fstat(journal.fileno())
                env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
                result = subprocess.run(
                    [sys.executable, "-m", "gateway", "run", "--config", str(config)],
                    stdout=subprocess.DEVNULL,
                    stderr=journal,
                    env=env,
                    timeout=60,
                    check=False,
                )
        assert result.returncode == 1
        lines = log_path.read_text().splitlines()
        assert lines
        assert all(line[:3] in ("<3>", "<4>", "<6>") for line in lines)
        failed = [line for line in lines if '"gateway_failed"' in line]
        assert failed
        assert failed[0].startswith("<3>{")


def read_until(stream: IO[str], event: str) -> Iterator[dict[str, Any]]:
    """Records from ``stream`` up to and including the first ``event``."""
    for line in stream:
        record = json.loads(line)
        yield record
        if record["event"] == event:
            return
    raise AssertionError(f"the process ended before logging {event}")


def test_sighup_checks_the_config_again_and_keeps_running(tmp_path: Path) -> None:
    config = udp_config(tmp_path, 0)
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway", "run", "--config", str(config)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert proc.stderr is not None
    assert proc.stdout is not None
    try:
        started = list(read_until(proc.stderr, "gateway_started"))
        # Start-up frozen and the young generation's threshold raised (gateway.ops.gcsetup).
        (settled,) = [r for r in started if r["event"] == "gc_settled"]
        assert settled["frozen_objects"] > 0
        assert settled["threshold"][0] == GEN0_THRESHOLD
        config.write_text(config.read_text().replace("node_id: n1", "node_id: n2"))
        proc.send_signal(signal.SIGHUP)
        *_, checked = read_until(proc.stderr, "config_reload_checked")
        assert (checked["changed"], checked["applied"]) == (["gateway"], False)
        assert checked["action"] == "restart to apply"
        config.write_text("gateway: {node_id: [}\n")
        proc.send_signal(signal.SIGHUP)
        *_, rejected = read_until(proc.stderr, "config_reload_rejected")
        assert rejected["issues"]
        assert proc.poll() is None  # neither check stopped it
        proc.send_signal(signal.SIGTERM)
        events = [r["event"] for r in read_until(proc.stderr, "gateway_stopped")]
        assert "gateway_stopped" in events
        assert proc.wait(timeout=10) == 0
        assert proc.stdout.read() == ""  # logs on stderr: stdout is for the console sink
    finally:
        proc.kill()
        proc.wait()
        proc.stderr.close()
        proc.stdout.close()


def test_check_config_warns_about_a_dem_source_it_cannot_use(tmp_path: Path) -> None:
    config = udp_config(tmp_path, 0)
    config.write_text(
        config.read_text()
        + "terrain:\n  sources:\n    - {name: lm, kind: hgt, sigma_m: 1, "
        + f"directory: '{tmp_path / 'absent'}'}}\n"
    )
    result = cli("check-config", str(config))
    assert result.returncode == 0, result.stderr
    assert f"{config}:7 terrain.sources[0]: source 'lm':" in result.stderr
    assert "(warning)" in result.stderr
    assert "is not a directory" in result.stderr


def test_check_config_takes_the_file_as_run_does_or_alone(tmp_path: Path) -> None:
    config = udp_config(tmp_path, 0)
    assert cli("check-config", "--config", str(config)).returncode == 0
    assert cli("check-config", str(config)).returncode == 0
    for args in ([], [str(config), "--config", str(config)]):
        result = cli("check-config", *args)
        assert result.returncode == 2
        assert "give one config file, as FILE or --config FILE" in result.stderr


class TestFiles:
    """What the wheel ships for installing without the source tree."""

    def test_out_writes_the_config_unit_and_docs_as_in_the_repository(self, tmp_path: Path) -> None:
        """As in the repository, but for the docs' relative links, which point at the copies."""
        result = cli("files", "--out", str(tmp_path / "share"))
        assert result.returncode == 0, result.stderr
        for name, source in {
            "example.yaml": "config/example.yaml",
            "fischer-gateway.service": "deploy/fischer-gateway.service",
            "INSTALL.md": "deploy/INSTALL.md",
            "operations.md": "docs/operations.md",
            "writing-a-sink.md": "docs/writing-a-sink.md",
        }.items():
            original = (ROOT / source).read_text()
            if name == "INSTALL.md":
                original = original.replace("](../docs/", "](")
            elif name == "operations.md":
                original = original.replace("](../deploy/INSTALL.md", "](INSTALL.md")
            assert (tmp_path / "share" / name).read_text() == original, name

    def test_one_file_is_printed_and_an_unknown_one_is_an_error(self) -> None:
        result = cli("files", "fischer-gateway.service")
        assert result.returncode == 0
        assert result.stdout == (ROOT / "deploy" / "fischer-gateway.service").read_text()
        result = cli("files", "nope")
        assert result.returncode == 2
        assert "example.yaml" in result.stderr
