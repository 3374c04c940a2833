"""The config's JSON Schema, for editors: the models' schema plus each installed sink's options.

``sinks[].options`` is an open object in the models (a sink type validates its own options),
so the schema adds, for every installed sink type, an ``if type == X then options: <X's
config model>`` branch: an editor then completes and checks a sink's options too. Properties
of the models all carry a description (a test keeps it so).
"""

from __future__ import annotations

from typing import Any

from gateway.c2.plugins import available, load_plugin
from gateway.config import Config
from gateway.errors import SinkLoadError
from gateway.ops.version import package_version

__all__ = ["SCHEMA_ID", "config_schema"]

#: An identifier, not an address: nothing is fetched from it.
SCHEMA_ID = "urn:fischer-gateway:config"


def config_schema() -> dict[str, Any]:
    """The JSON Schema (2020-12) of the config file, with per-sink option schemas."""
    schema = Config.model_json_schema(mode="validation")
    defs: dict[str, Any] = schema.setdefault("$defs", {})
    branches = []
    for type_name in sorted(available()):
        try:
            plugin = load_plugin(type_name)
        except SinkLoadError:
            continue  # a broken plugin: check-config names it; the schema goes without it
        options = plugin.factory.config_model.model_json_schema(ref_template="#/$defs/{model}")
        defs.update(options.pop("$defs", {}))
        name = f"sink_options_{type_name}"
        defs[name] = options
        branches.append(
            {
                "if": {"properties": {"type": {"const": type_name}}, "required": ["type"]},
                "then": {"properties": {"options": {"$ref": f"#/$defs/{name}"}}},
            }
        )
    if "SinkEntry" in defs and branches:
        defs["SinkEntry"]["allOf"] = branches
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": SCHEMA_ID,
        "title": f"fischer-gateway {package_version()} configuration",
        **schema,
    }
