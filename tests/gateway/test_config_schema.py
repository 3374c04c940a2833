"""The JSON Schema editors use: valid 2020-12, every property described, sink options checked."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml
from own_plugins import own_types

from gateway.c2.plugins import GROUP, PROCESSOR_GROUP, SOURCE_GROUP

ROOT = Path(__file__).resolve().parents[2]
#: The ``$defs`` holding the options of the plugin types we ship.
OWN_OPTIONS = {
    *(f"sink_options_{t}" for t in own_types(GROUP)),
    *(f"processors_options_{t}" for t in own_types(PROCESSOR_GROUP)),
    *(f"sources_options_{t}" for t in own_types(SOURCE_GROUP)),
}
PLUGIN_OPTIONS = re.compile(r"(sink|processors|sources)_options_")


def own_defs(schema: dict[str, Any]) -> set[str]:
    """The ``$defs`` the config and the plugins we ship use, not a third-party plugin's."""
    found: set[str] = set()
    todo: list[Any] = [{k: v for k, v in schema.items() if k != "$defs"}]
    while todo:
        node = todo.pop()
        if isinstance(node, dict):
            ref = node.get("$ref")
            if isinstance(ref, str) and ref.startswith("#/$defs/"):
                name = ref.removeprefix("#/$defs/")
                if name not in found and (not PLUGIN_OPTIONS.match(name) or name in OWN_OPTIONS):
                    found.add(name)
                    todo.append(schema["$defs"][name])
            todo.extend(node.values())
        elif isinstance(node, list):
            todo.extend(node)
    return found


@pytest.fixture(scope="module")
def schema() -> dict[str, Any]:
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "config-schema"],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return json.loads(result.stdout)  # type: ignore[no-any-return]


def test_it_is_a_2020_12_schema_with_an_id(schema: dict[str, Any]) -> None:
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["$id"].startswith("urn:fischer-gateway:")
    jsonschema.Draft202012Validator.check_schema(schema)


def test_every_property_including_the_shipped_sinks_options_has_a_description(
    schema: dict[str, Any],
) -> None:
    # A third-party plugin installed beside us is not ours to judge.
    ours = own_defs(schema)
    assert ours >= OWN_OPTIONS
    bare = [
        f"{name}.{prop}"
        for name, model in [("Config", schema), *schema["$defs"].items()]
        if name == "Config" or name in ours
        for prop, spec in model.get("properties", {}).items()
        if "description" not in spec
    ]
    assert bare == []


def test_the_example_config_validates(schema: dict[str, Any]) -> None:
    data = yaml.safe_load((ROOT / "config" / "example.yaml").read_text())
    jsonschema.Draft202012Validator(schema).validate(data)


def test_a_sink_option_typo_is_caught_by_the_schema(schema: dict[str, Any]) -> None:
    data = {
        "airframes": [
            {"id": "A", "sysid": 1, "links": [{"uri": "udp://127.0.0.1:1", "security": "tunnel"}]}
        ],
        "sinks": [{"name": "a", "type": "jsonl", "options": {"path": "a.jsonl", "max_byte": 1}}],
    }
    errors = list(jsonschema.Draft202012Validator(schema).iter_errors(data))
    assert any("max_byte" in error.message for error in errors)
    data["sinks"][0]["options"] = {"path": "a.jsonl", "max_bytes": 4096}
    assert list(jsonschema.Draft202012Validator(schema).iter_errors(data)) == []
