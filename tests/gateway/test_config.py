"""Config loading: every problem reported with file, line and key path."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.c2.plugins import check_sink
from gateway.cli import main
from gateway.config import parse_endpoint
from gateway.configfile import load_config, load_config_text
from gateway.errors import ConfigError
from gateway.testing import fuzz_examples

GOOD = textwrap.dedent(
    """\
    gateway:
      node_id: node-1
    airframes:
      - id: F26E-001
        sysid: 1
        links:
          - uri: udp://127.0.0.1:14550
            security: unsecured
      - id: F26E-002
        sysid: 2
        links:
          - uri: tcp://10.0.0.2:5760
            security: unsecured
            priority: 1
          - uri: serial:///dev/ttyUSB0?baud=115200
            security: unsecured
    sinks:
      - name: archive
        type: jsonl
        options:
          path: /tmp/archive.jsonl
      - name: mem
        type: memory
    routes:
      - sinks: [archive, mem]
        kinds: [telemetry, detection]
        airframes: [F26E-001]
        max_rate_hz: 1
    """
)

BAD = textwrap.dedent(
    """\
    gateway:
      node_id: node-1
    airframes:
      - id: F26E-001
        sysid: 1
        links:
          - uri: udp://127.0.0.1:14550
            security: unsecured
            priorty: 2
      - id: F26E-002
        sysid: 1
        links:
          - uri: htp://10.0.0.2:5760
            security: unsecured
    sinks:
      - name: mem
        type: memory
    routes:
      - sinks: [mem, nowhere]
    """
)


class TestLoad:
    """Loading a valid config and reading its values."""

    def test_good_config_loads_with_parsed_links(self) -> None:
        config = load_config_text(GOOD, "good.yaml", check_sink=check_sink)
        assert config.gateway.node_id == "node-1"
        tcp = config.airframes[1].links[0].uri
        assert (tcp.scheme, tcp.mode, tcp.host, tcp.port) == ("tcp", "connect", "10.0.0.2", 5760)
        serial = config.airframes[1].links[1].uri
        assert (serial.device, serial.baud) == ("/dev/ttyUSB0", 115200)
        assert config.routes[0].max_rate_hz == 1

    def test_config_is_frozen(self) -> None:
        config = load_config_text(GOOD)
        with pytest.raises(ValueError, match="frozen"):
            config.gateway.node_id = "x"  # type: ignore[misc]

    def test_empty_file_is_an_error_not_an_idle_daemon(self) -> None:
        """An empty file would bind the health port and do nothing: say so instead."""
        with pytest.raises(ConfigError, match="nothing to do: no airframes and no sources"):
            load_config_text("")

    def test_unknown_keys_get_a_did_you_mean(self) -> None:
        text = "airframes:\n  - {id: A, sysid: 1, link_timout_s: 3, links: []}\nhealht: {}\n"
        with pytest.raises(ConfigError) as info:
            load_config_text(text, "t.yaml")
        messages = {issue.key_path: issue.message for issue in info.value.issues}
        assert "did you mean 'link_timeout_s'?" in messages["airframes[0].link_timout_s"]
        assert "did you mean 'health'?" in messages["healht"]

    def test_a_missing_security_names_the_choices(self) -> None:
        text = "airframes:\n  - {id: A, sysid: 1, links: [{uri: 'udp://127.0.0.1:1'}]}\n"
        with pytest.raises(ConfigError) as info:
            load_config_text(text, "t.yaml")
        (issue,) = info.value.issues
        assert issue.key_path == "airframes[0].links[0].security"
        assert "one of tunnel, signed, unsecured" in issue.message

    @pytest.mark.parametrize(
        ("uri", "message"),
        [
            ("tcp://192.0.2.300:5760", "expected an IP address or a host name"),
            ("tcp://bad_host!:5760", "expected an IP address or a host name"),
            ("serial:///dev/ttyUSB0?baud=57601", "expected a standard baud rate"),
            ("serial:///dev/ttyUSB0?baud=%C2%B2", "expected a standard baud rate"),
        ],
    )
    def test_uris_that_could_never_open_are_config_errors(self, uri: str, message: str) -> None:
        text = (
            f"airframes:\n  - {{id: A, sysid: 1, links: [{{uri: '{uri}', security: unsecured}}]}}\n"
        )
        with pytest.raises(ConfigError, match=message):
            load_config_text(text, "t.yaml")


class TestErrors:
    """Every error is reported, each with its line and key path."""

    def test_typo_bad_uri_and_duplicate_sysid_are_all_reported_with_lines(self) -> None:
        with pytest.raises(ConfigError) as info:
            load_config_text(BAD, "bad.yaml")
        by_key = {issue.key_path: issue for issue in info.value.issues}
        assert by_key["airframes[0].links[0].priorty"].line == 9
        assert "unknown key 'priorty'" in by_key["airframes[0].links[0].priorty"].message
        assert by_key["airframes[1].sysid"].line == 11
        assert "duplicate sysid 1" in by_key["airframes[1].sysid"].message
        assert by_key["airframes[1].links[0].uri"].line == 13
        assert "expected udp://, tcp:// or serial://" in by_key["airframes[1].links[0].uri"].message
        assert "htp://10.0.0.2:5760" in by_key["airframes[1].links[0].uri"].message
        assert by_key["routes[0].sinks[1]"].line == 19
        assert str(by_key["airframes[1].sysid"]).startswith("bad.yaml:11 airframes[1].sysid: ")

    def test_unknown_sink_type_and_bad_options_are_reported(self) -> None:
        text = textwrap.dedent(
            """\
            sinks:
              - name: a
                type: nosuchsink
              - name: b
                type: jsonl
                options:
                  path: /tmp/x.jsonl
                  max_bytez: 10
            """
        )
        with pytest.raises(ConfigError) as info:
            load_config_text(text, "s.yaml", check_sink=check_sink)
        by_key = {issue.key_path: issue for issue in info.value.issues}
        assert by_key["sinks[0].type"].line == 3
        assert "unknown sink type 'nosuchsink'" in by_key["sinks[0].type"].message
        assert "jsonl" in by_key["sinks[0].type"].message
        assert by_key["sinks[1].options.max_bytez"].line == 8

    def test_duplicate_yaml_key_is_an_error(self) -> None:
        with pytest.raises(ConfigError) as info:
            load_config_text(
                "gateway:\n  node_id: a\n  node_id: b\nsources: [{name: s, uri: 'udp://239.2.3.1:6969'}]\n",
                "d.yaml",
            )
        (issue,) = info.value.issues
        assert (issue.line, issue.key_path) == (3, "gateway.node_id")

    def test_invalid_yaml_names_the_line(self) -> None:
        with pytest.raises(ConfigError) as info:
            load_config_text("gateway:\n  node_id: [unclosed\n", "y.yaml")
        assert info.value.issues[0].line is not None

    def test_missing_file_is_a_config_error(self, tmp_path: Path) -> None:
        with pytest.raises(ConfigError, match="cannot read"):
            load_config(tmp_path / "absent.yaml")

    @pytest.mark.parametrize(
        ("uri", "expected"),
        [
            ("udp://127.0.0.1", "HOST:PORT"),
            ("udp://127.0.0.1:99999", "port"),
            ("udp://127.0.0.1:14550?mode=sideways", "mode=listen or mode=connect"),
            ("tcp://127.0.0.1:1?baud=9600", "only 'mode'"),
            ("serial://dev/ttyUSB0", "serial:///dev/DEVICE"),
            ("serial:///dev/ttyUSB0?baud=fast", "baud"),
        ],
    )
    def test_bad_uris_say_what_was_expected(self, uri: str, expected: str) -> None:
        with pytest.raises(ValueError, match=expected):
            parse_endpoint(uri)


class TestCli:
    """check-config and config-schema as an operator runs them."""

    def test_check_config_exits_2_and_prints_every_error(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str]
    ) -> None:
        path = tmp_path / "bad.yaml"
        path.write_text(BAD)
        assert main(["check-config", str(path)]) == 2
        err = capsys.readouterr().err
        assert f"{path}:9 airframes[0].links[0].priorty" in err
        assert f"{path}:11 airframes[1].sysid" in err
        assert f"{path}:13 airframes[1].links[0].uri" in err
        assert "4 error(s)" in err

    def test_check_config_lists_sinks_with_distribution(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str]
    ) -> None:
        path = tmp_path / "good.yaml"
        path.write_text(GOOD)
        assert main(["check-config", str(path)]) == 0
        out = capsys.readouterr().out
        assert "sink archive: type jsonl from fischer-gateway 0.1.0" in out
        assert "sink mem: type memory from fischer-gateway" in out

    def test_route_sending_a_kind_the_sink_refuses_is_an_error(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str]
    ) -> None:
        path = tmp_path / "kinds.yaml"
        path.write_text(
            "sinks:\n  - name: m\n    type: memory\n    options: {kinds: [telemetry]}\n"
            "routes:\n  - sinks: [m]\n    kinds: [detection]\n"
        )
        assert main(["check-config", str(path)]) == 2
        assert "does not accept 'detection'" in capsys.readouterr().err

    def test_config_schema_is_json_schema_of_the_models(
        self, capsys: pytest.CaptureFixture[str]
    ) -> None:
        assert main(["config-schema"]) == 0
        schema = json.loads(capsys.readouterr().out)
        assert set(schema["properties"]) == {
            "gateway",
            "health",
            "tunnel",
            "terrain",
            "spool",
            "sources",
            "processors",
            "airframes",
            "sinks",
            "routes",
        }
        assert schema["$defs"]["LinkConfig"]["properties"]["uri"]["type"] == "string"

    def test_example_config_is_valid(self) -> None:
        example = Path(__file__).parents[2] / "config" / "example.yaml"
        config = load_config(example, check_sink=check_sink)
        assert config.airframes


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(st.text(max_size=400) | st.binary(max_size=400).map(lambda b: b.decode("latin-1")))
def test_arbitrary_text_gives_a_config_or_a_config_error(text: str) -> None:
    """The loader's only failure is ConfigError, whatever the file holds."""
    try:
        load_config_text(text, "fuzz.yaml", check_sink=check_sink)
    except ConfigError as exc:
        issues = exc.issues
    else:
        return
    assert issues
    assert all(issue.source == "fuzz.yaml" for issue in issues)


def test_replay_to_a_non_udp_target_is_a_usage_error(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Logging set up by the CLI would cache pytest's capture stream, closed after the test.
    monkeypatch.setattr("gateway.cli.configure_logging", lambda *a, **k: None)
    assert main(["replay", "/dev/null", "--to", "tcp://127.0.0.1:1"]) == 2
    assert "--to: expected udp://HOST:PORT" in capsys.readouterr().err


def test_source_and_processor_names_are_unique() -> None:
    text = "sources:\n  - {name: a, uri: 'udp://127.0.0.1:1'}\n  - {name: a, uri: 'udp://127.0.0.1:2'}\n"
    with pytest.raises(ConfigError, match=r"duplicate name 'a', already used by sources\[0\]"):
        load_config_text(text, "s.yaml")
