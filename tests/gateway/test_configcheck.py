"""``check-config`` as an operator runs it: every problem in one pass, with its line, exit 2.

Each test runs ``python -m gateway check-config`` (or ``run``) in a child process, as the unit's
``ExecStartPre=`` and an operator at a shell do.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={**os.environ, **(env or {})},
    )


def key(path: Path, data: bytes = bytes(range(32))) -> Path:
    path.write_text(data.hex())
    path.chmod(0o600)
    return path


def test_the_readme_example_passes_away_from_the_node() -> None:
    result = cli("check-config", "--no-environment", str(ROOT / "config" / "example.yaml"))
    assert result.returncode == 0, result.stderr
    assert "ok (2 airframes" in result.stdout


def test_the_credential_is_a_warning_outside_systemd_and_an_error_when_missing_inside(
    tmp_path: Path,
) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(
        "tunnel: {master_key_credential: tunnel-master}\n"
        "airframes:\n  - {id: A, sysid: 1, links: "
        "[{uri: 'udp://127.0.0.1:14550', security: tunnel}]}\n"
    )
    outside = cli("check-config", str(config), env={"CREDENTIALS_DIRECTORY": ""})
    assert outside.returncode == 0, outside.stderr
    assert f"{config}:1 tunnel.master_key_credential:" in outside.stderr
    assert "(warning)" in outside.stderr
    (tmp_path / "creds").mkdir()
    inside = cli(
        "check-config", str(config), env={"CREDENTIALS_DIRECTORY": str(tmp_path / "creds")}
    )
    assert inside.returncode == 2
    assert f"{config}:1 tunnel.master_key_credential:" in inside.stderr
    key(tmp_path / "creds" / "tunnel-master")
    assert (
        cli(
            "check-config", str(config), env={"CREDENTIALS_DIRECTORY": str(tmp_path / "creds")}
        ).returncode
        == 0
    )


def test_every_kind_of_problem_comes_in_one_pass_with_lines(tmp_path: Path) -> None:
    """Schema, key files, sink files and routes: once, not in rounds."""
    wide_open = key(tmp_path / "signing.key")
    wide_open.chmod(0o644)
    config = tmp_path / "c.yaml"
    config.write_text(
        f"""tunnel: {{master_key_file: '{tmp_path / "absent.key"}'}}
airframes:
  - id: A
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:14550', security: tunnel}}]
  - id: B
    sysid: 2
    signing: {{key_file: '{wide_open}'}}
    links: [{{uri: 'udp://127.0.0.1:14551', security: signed}}]
    link_timout_s: 2
sinks:
  - name: tak
    type: cot
    options:
      geoid_file: '{tmp_path / "egm96_15.gtx"}'
      destinations: ['udp://127.0.0.1:6969']
  - name: tak2
    type: cot
    options:
      destinations:
        - uri: 'tls://127.0.0.1:8089'
          tls: {{ca_file: '{tmp_path / "ca.pem"}', cert_file: '{tmp_path / "client.pem"}'}}
  - {{name: archive, type: jsonl, options: {{path: '{tmp_path / "a.jsonl"}', kinds: [telemetry]}}}}
routes:
  - {{sinks: [archive], kinds: [detection]}}
"""
    )
    result = cli("check-config", str(config))
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.startswith(str(config))]
    expected = [
        ":1 tunnel.master_key_file:",  # missing
        ":8 airframes[1].signing.key_file:",  # mode 644
        ":10 airframes[1].link_timout_s: unknown key 'link_timout_s'; did you mean",
        ":14 sinks[0].options:",  # the geoid file
        ":22 sinks[1].options.destinations[0].tls:",  # the CA
        ":25 routes[0].kinds[0]: sink 'archive' does not accept 'detection'",
    ]
    for fragment in expected:
        assert any(fragment in line for line in lines), (fragment, result.stderr)
    assert "Traceback" not in result.stderr + result.stdout
    assert "mode is 644" in result.stderr
    assert "egm96_15.gtx" in result.stderr
    assert "ca.pem" in result.stderr


FAKE_SINKS = """
from gateway.events import EventKind
from gateway.c2.sink import SinkConfig


class NoName:
    config_model = SinkConfig

    def __init__(self) -> None:  # wrong: a sink is built as Sink(name, config)
        pass

    async def open(self) -> None: ...
    async def send(self, batch) -> None: ...
    async def aclose(self) -> None: ...


class StringKinds:
    config_model = SinkConfig

    def __init__(self, name, config) -> None:
        self.name = name
        self.kinds = frozenset({"telemetry"})  # wrong: EventKind members

    async def open(self) -> None: ...
    async def send(self, batch) -> None: ...
    async def aclose(self) -> None: ...
"""


def test_broken_third_party_sinks_are_config_errors_naming_the_sink(tmp_path: Path) -> None:
    site = tmp_path / "site"
    dist = site / "fake_sinks-0.1.dist-info"
    dist.mkdir(parents=True)
    (site / "fake_sinks.py").write_text(FAKE_SINKS)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: fake-sinks\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(
        "[fischer_gateway.sinks]\nnoname = fake_sinks:NoName\nstrkinds = fake_sinks:StringKinds\n"
    )
    config = tmp_path / "c.yaml"
    config.write_text(
        "airframes:\n  - {id: A, sysid: 1, links: [{uri: 'udp://127.0.0.1:14550', "
        "security: unsecured}]}\n"
        "sinks:\n  - {name: one, type: noname}\n  - {name: two, type: strkinds}\n"
        "routes:\n  - {sinks: [one, two]}\n"
    )
    env = {"PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    for command in (["check-config", str(config)], ["run", "--config", str(config)]):
        result = cli(*command, env=env)
        assert result.returncode == 2, result.stderr
        assert f"{config}:4 sinks[0].type: sink type 'noname' from fake-sinks 0.1" in result.stderr
        assert "factory(name, config)" in result.stderr
        assert (
            f"{config}:5 sinks[1].type: sink type 'strkinds' from fake-sinks 0.1" in result.stderr
        )
        assert "EventKind" in result.stderr
        assert "Traceback" not in result.stderr


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "nothing to do"),
        (
            "airframes:\n  - {id: A, sysid: 1, links: [{uri: 'tcp://192.0.2.300:5760', "
            "security: unsecured}]}\n",
            "expected an IP address or a host name",
        ),
        (
            "airframes:\n  - {id: A, sysid: 1, links: [{uri: 'serial:///dev/ttyUSB0?baud=57601', "
            "security: unsecured}]}\n",
            "expected a standard baud rate",
        ),
    ],
)
def test_configs_that_used_to_start_and_then_fail_are_refused(
    tmp_path: Path, text: str, message: str
) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(text)
    for command in (["check-config", str(config)], ["run", "--config", str(config)]):
        result = cli(*command)
        assert result.returncode == 2, result.stderr
        assert message in result.stderr


def test_a_serial_device_not_plugged_in_is_a_warning(tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(
        "airframes:\n  - {id: A, sysid: 1, links: "
        f"[{{uri: 'serial://{tmp_path / 'radio'}?baud=57600', security: unsecured}}]}}\n"
    )
    result = cli("check-config", str(config))
    assert result.returncode == 0, result.stderr
    assert "does not exist now; the link will wait for it (warning)" in result.stderr


def test_a_directory_where_a_file_belongs_is_exit_2_naming_it(tmp_path: Path) -> None:
    """The unit's RestartPreventExitStatus=2 stops a restart loop only if this is exit 2."""
    directory = tmp_path / "conf.d"
    directory.mkdir()
    result = cli("check-config", str(directory))
    assert result.returncode == 2
    assert f"{directory} (file): a directory" in result.stderr
    config = tmp_path / "c.yaml"
    config.write_text(
        f"tunnel: {{master_key_file: '{directory}'}}\n"
        "airframes:\n  - {id: A, sysid: 1, links: "
        "[{uri: 'udp://127.0.0.1:14550', security: tunnel}]}\n"
    )
    for command in (["check-config", str(config)], ["run", "--config", str(config)]):
        result = cli(*command)
        assert result.returncode == 2, result.stderr
        assert "key file is a directory" in result.stderr
        assert "Traceback" not in result.stderr


def test_a_proc_file_is_not_a_key(tmp_path: Path) -> None:
    """/proc files say "regular, 0 bytes" and then produce text; none is a key."""
    config = tmp_path / "c.yaml"
    config.write_text(
        "tunnel: {master_key_file: /proc/self/environ}\n"
        "airframes:\n  - {id: A, sysid: 1, links: "
        "[{uri: 'udp://127.0.0.1:14550', security: tunnel}]}\n"
    )
    result = cli("check-config", str(config))
    assert result.returncode == 2
    assert "not a regular file" in result.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["keys", "new", "--out", "/nonexistent/m.key"], "/nonexistent/m.key: No such file"),
        (
            ["keys", "derive", "--master", "m", "--airframe", "../evil", "--from", "2026-11-23",
             "--out", "kd"],
            "expected an airframe id",
        ),
        (["replay", "/nonexistent.tlog", "--to", "udp://127.0.0.1:9"], "no such .tlog file"),
    ],
)  # fmt: skip
def test_command_line_mistakes_are_exit_2_without_a_traceback(
    tmp_path: Path, args: list[str], message: str
) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "gateway", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=tmp_path,
    )
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path.parent / "evil-2026-11-23.key").exists()


def test_a_dem_source_whose_every_tile_is_unreadable_is_a_warning_and_disabled(
    tmp_path: Path,
) -> None:
    dem = tmp_path / "dem"
    dem.mkdir()
    (dem / "x.tif").write_bytes(b"not a tiff at all")
    config = tmp_path / "c.yaml"
    config.write_text(
        "airframes:\n  - {id: A, sysid: 1, links: "
        "[{uri: 'udp://127.0.0.1:14550', security: unsecured}]}\n"
        f"terrain:\n  sources:\n    - {{name: lm, kind: geotiff, sigma_m: 1, directory: '{dem}'}}\n"
    )
    result = cli("check-config", str(config))
    assert result.returncode == 0
    assert "every tile is unreadable" in result.stderr


def test_a_passthrough_must_state_its_uplink_and_keep_its_own_key(tmp_path: Path) -> None:
    """Issue 21: no default uplink; the fix is in the message; a ground station never holds
    the airframe's own signing key; beyond loopback only when stated. ``run`` refuses the
    same file with the same lines."""
    airframe_key = key(tmp_path / "sig.key")
    config = tmp_path / "c.yaml"
    config.write_text(
        "airframes:\n"
        "  - id: A\n    sysid: 1\n"
        "    passthrough: udp://127.0.0.1:14560\n"
        "    links: [{uri: 'udp://127.0.0.1:14550', security: unsecured}]\n"
        "  - id: B\n    sysid: 2\n"
        "    passthrough: {uri: 'udp://127.0.0.1:14561'}\n"
        "    links: [{uri: 'udp://127.0.0.1:14551', security: unsecured}]\n"
        "  - id: C\n    sysid: 3\n"
        f"    signing: {{key_file: '{airframe_key}'}}\n"
        f"    passthrough: {{uri: 'udp://127.0.0.1:14562', uplink: signed,\n"
        f"                  key_file: '{airframe_key}'}}\n"
        "    links: [{uri: 'udp://127.0.0.1:14552', security: signed}]\n"
        "  - id: D\n    sysid: 4\n"
        "    passthrough: {uri: 'udp://0.0.0.0:14563', uplink: none}\n"
        "    links: [{uri: 'udp://127.0.0.1:14553', security: unsecured}]\n"
        # Nor another airframe's: it could sign straight to C around the policy.
        "  - id: E\n    sysid: 5\n"
        "    passthrough: {uri: 'udp://127.0.0.1:14564', uplink: signed,\n"
        f"                  key_file: '{airframe_key}'}}\n"
        "    links: [{uri: 'udp://127.0.0.1:14554', security: unsecured}]\n"
    )
    result = cli("check-config", "--no-environment", str(config))
    assert result.returncode == 2
    assert f"{config}:4 airframes[0].passthrough: the passthrough must state" in result.stderr
    assert "uplink: none|signed|open" in result.stderr
    assert f"{config}:8 airframes[1].passthrough.uplink: missing required key" in result.stderr
    assert f"{config}:18 airframes[3].passthrough.uri: '0.0.0.0' is beyond loopback" in (
        result.stderr
    )
    # On the node (and so at ``run``), once the file itself is good: the key check.
    text = config.read_text()
    text = text.replace(
        "passthrough: udp://127.0.0.1:14560",
        "passthrough: {uri: 'udp://127.0.0.1:14560', uplink: none}",
    )
    text = text.replace(
        "{uri: 'udp://127.0.0.1:14561'}", "{uri: 'udp://127.0.0.1:14561', uplink: open}"
    )
    text = text.replace("0.0.0.0:14563", "127.0.0.1:14563")
    config.write_text(text)
    for command in ("check-config", "run"):
        args = ("--config", str(config)) if command == "run" else (str(config),)
        result = cli(command, *args)
        assert result.returncode == 2, result.stderr
        assert f"{config}:14 airframes[2].passthrough.key_file:" in result.stderr
        assert "is the airframe's signing key" in result.stderr
        assert f"{config}:23 airframes[4].passthrough.key_file:" in result.stderr
        assert "is airframe C's signing key" in result.stderr
