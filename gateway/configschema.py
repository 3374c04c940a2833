"""The config's JSON Schema, for editors: the models' schema plus each installed sink's options.

``sinks[].options`` is an open object in the models (a sink type validates its own options),
so the schema adds, for every installed sink type, an ``if type == X then options: <X's
config model>`` branch: an editor then completes and checks a sink's options too. Properties
of the models all carry a description (a test keeps it so).
"""

from __future__ import annotations

from importlib.metadata import entry_points
from typing import Any

from gateway.c2.plugins import (
    PROCESSOR_GROUP,
    SOURCE_GROUP,
    available,
    load_component,
    load_plugin,
)
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
    for group, entry_def, inline in (
        (PROCESSOR_GROUP, "ProcessorEntry", False),
        (SOURCE_GROUP, "SourceEntry", True),
    ):
        component_branches = []
        for ep in sorted(entry_points(group=group), key=lambda ep: ep.name):
            try:
                component = load_component(group, ep.name)
            except SinkLoadError:
                continue
            options = component.model.model_json_schema(ref_template="#/$defs/{model}")
            defs.update(options.pop("$defs", {}))
            name = f"{group.rsplit('.', 1)[1]}_options_{ep.name}"
            defs[name] = options
            # Sources take their options beside name and type; processors under options.
            if inline and options.get("additionalProperties") is False:
                # Beside a source's own options stand the entry's name and type.
                options["properties"] = {
                    "name": {"type": "string", "description": "The source's name."},
                    "type": {"type": "string", "description": "The source type."},
                    **options.get("properties", {}),
                }
            then = (
                {"$ref": f"#/$defs/{name}"}
                if inline
                else {"properties": {"options": {"$ref": f"#/$defs/{name}"}}}
            )
            component_branches.append(
                {"if": {"properties": {"type": {"const": ep.name}}}, "then": then}
            )
        if entry_def in defs and component_branches:
            defs[entry_def]["allOf"] = component_branches
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": SCHEMA_ID,
        "title": f"fischer-gateway {package_version()} configuration",
        **schema,
    }
