"""The systemd unit keeps the promises the README and INSTALL.md make."""

from __future__ import annotations

from configparser import ConfigParser
from pathlib import Path

from gateway.config import GatewayConfig

UNIT = Path(__file__).resolve().parents[1] / "deploy" / "fischer-gateway.service"


def service() -> dict[str, list[str]]:
    values: dict[str, list[str]] = {}
    section = ""
    for raw in UNIT.read_text().splitlines():
        line = raw.strip()
        if line.startswith("["):
            section = line
        elif section == "[Service]" and "=" in line and not line.startswith("#"):
            key, _, value = line.partition("=")
            values.setdefault(key, []).append(value)
    return values


def test_unit_is_notify_with_watchdog_and_config_check() -> None:
    s = service()
    assert s["Type"] == ["notify"]
    assert int(s["WatchdogSec"][0]) > 0
    assert "check-config" in s["ExecStartPre"][0]
    assert s["RestartPreventExitStatus"] == ["2"]


def test_stop_timeout_exceeds_the_default_shutdown_deadline() -> None:
    assert int(service()["TimeoutStopSec"][0]) > GatewayConfig().shutdown_deadline_s


def test_unit_is_sandboxed() -> None:
    s = service()
    for key, value in {
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "CapabilityBoundingSet": "",
    }.items():
        assert s[key] == [value], key
    assert "tunnel-master:" in s["LoadCredential"][0]


def test_unit_parses_as_ini() -> None:
    parser = ConfigParser(strict=False, interpolation=None)
    parser.read_string(UNIT.read_text())
    assert {"Unit", "Service", "Install"} <= set(parser.sections())


def test_reload_sends_sighup_which_the_cli_handles() -> None:
    """ExecReload= matches what the daemon does with SIGHUP (gateway/cli.py, reload.py)."""
    assert service()["ExecReload"] == ["/bin/kill -HUP $MAINPID"]
    cli = (UNIT.parents[1] / "gateway" / "cli.py").read_text()
    assert "signal.SIGHUP" in cli
