"""The JSON Schema editors use: valid 2020-12, every property described, sink options checked."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]


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
    bare = [
        f"{name}.{prop}"
        for name, model in [("Config", schema), *schema["$defs"].items()]
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
