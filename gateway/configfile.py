"""Loading the config file: YAML with line numbers, every problem reported at once.

``load_config`` reports every problem it finds, each as ``FILE:LINE key.path: what was
expected, what was found``, by raising one ``ConfigError``: pydantic's validation errors,
duplicate YAML keys, and the checks across items (duplicate sysids, routes naming sinks
that do not exist, links whose security needs a key that is not configured ...).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from gateway.config import Config
from gateway.errors import ConfigError, ConfigIssue, SinkLoadError

__all__ = ["SinkChecker", "format_loc", "load_config", "load_config_text"]

Loc = tuple[str | int, ...]


def format_loc(loc: Loc) -> str:
    """``('airframes', 0, 'links', 1, 'uri')`` → ``airframes[0].links[1].uri``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out or "(top level)"


class _Lines:
    """Line numbers (1-based) of every key and item of a composed YAML document."""

    def __init__(self) -> None:
        self.by_loc: dict[Loc, int] = {(): 1}
        self.duplicates: list[tuple[Loc, int]] = []

    def walk(self, node: yaml.Node, loc: Loc) -> None:
        self.by_loc.setdefault(loc, node.start_mark.line + 1)
        if isinstance(node, yaml.MappingNode):
            seen: set[str] = set()
            for key_node, value_node in node.value:
                key = str(key_node.value)
                child = (*loc, key)
                if key in seen:
                    self.duplicates.append((child, key_node.start_mark.line + 1))
                    continue
                seen.add(key)
                self.by_loc[child] = key_node.start_mark.line + 1
                self.walk(value_node, child)
        elif isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                self.walk(item, (*loc, index))

    def line(self, loc: Loc) -> int:
        while loc not in self.by_loc:
            loc = loc[:-1]
        return self.by_loc[loc]


def _found(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _issues_from_validation(exc: ValidationError, prefix: Loc) -> Iterator[tuple[Loc, str]]:
    errors = exc.errors()
    inner = {tuple(e["loc"][:n]) for e in errors for n in range(len(e["loc"]))}
    for error in errors:
        if error["type"] == "too_short" and tuple(error["loc"]) in inner:
            # pydantic also reports a list as too short when one of its items failed.
            continue
        loc: Loc = (*prefix, *error["loc"])
        message = error["msg"].removeprefix("Value error, ")
        if error["type"] == "extra_forbidden":
            message = f"unknown key '{loc[-1]}' (a typo?); expected one of the documented keys"
        elif error["type"] != "missing" and "found" not in message:
            message = f"{message}, found {_found(error.get('input'))}"
        yield loc, message


def _cross_check(data: dict[str, Any]) -> Iterator[tuple[Loc, str]]:
    """Checks across items, made on the raw data so they report even if other items fail."""
    airframes = data.get("airframes")
    ids: dict[object, int] = {}
    sysids: dict[object, int] = {}
    if isinstance(airframes, list):
        for i, item in enumerate(airframes):
            if not isinstance(item, dict):
                continue
            for key, seen in (("id", ids), ("sysid", sysids)):
                value = item.get(key)
                if value is None:
                    continue
                if value in seen:
                    yield (
                        ("airframes", i, key),
                        (f"duplicate {key} {value!r}, already used by airframes[{seen[value]}]"),
                    )
                else:
                    seen[value] = i
    sink_names: dict[object, int] = {}
    sinks = data.get("sinks")
    if isinstance(sinks, list):
        for i, item in enumerate(sinks):
            if isinstance(item, dict) and "name" in item:
                if item["name"] in sink_names:
                    yield (
                        ("sinks", i, "name"),
                        (
                            f"duplicate sink name {item['name']!r}, already used by "
                            f"sinks[{sink_names[item['name']]}]"
                        ),
                    )
                else:
                    sink_names[item["name"]] = i
    routes = data.get("routes")
    if isinstance(routes, list):
        for i, route in enumerate(routes):
            if not isinstance(route, dict):
                continue
            for j, name in enumerate(route.get("sinks") or ()):
                if name not in sink_names:
                    yield (
                        ("routes", i, "sinks", j),
                        (f"expected the name of a configured sink, found {name!r}"),
                    )
            for j, name in enumerate(route.get("airframes") or ()):
                if name != "*" and name not in ids:
                    yield (
                        ("routes", i, "airframes", j),
                        (f"expected the id of a configured airframe, found {name!r}"),
                    )


def _link_checks(data: dict[str, Any]) -> Iterator[tuple[Loc, str]]:
    """Links shared by airframes must agree; each security mode needs its key configured."""
    airframes = data.get("airframes")
    if not isinstance(airframes, list):
        return
    tunnel = data.get("tunnel")
    if not isinstance(tunnel, dict):
        tunnel = {}
    has_master = bool(tunnel.get("master_key_file") or tunnel.get("master_key_credential"))
    by_uri: dict[str, tuple[object, object, Loc]] = {}
    by_name: dict[object, tuple[str, Loc]] = {}
    for i, airframe in enumerate(airframes):
        if not isinstance(airframe, dict):
            continue
        passthrough = airframe.get("passthrough")
        if isinstance(passthrough, str) and not passthrough.startswith("udp://"):
            yield (
                ("airframes", i, "passthrough"),
                (f"expected a udp:// endpoint for the passthrough, found {passthrough!r}"),
            )
        links = airframe.get("links")
        for j, link in enumerate(links if isinstance(links, list) else ()):
            if not isinstance(link, dict) or not isinstance(link.get("uri"), str):
                continue
            loc: Loc = ("airframes", i, "links", j)
            uri, security, name = link["uri"], link.get("security"), link.get("name")
            if security == "tunnel" and not has_master:
                yield (
                    (*loc, "security"),
                    ("a tunnel link needs tunnel.master_key_file or tunnel.master_key_credential"),
                )
            if security == "signed" and not airframe.get("signing"):
                yield (*loc, "security"), "a signed link needs the airframe's 'signing' section"
            seen = by_uri.get(uri)
            if seen is None:
                by_uri[uri] = (security, name, loc)
            elif seen[0] != security:
                yield (
                    (*loc, "security"),
                    (
                        f"{uri} is shared with {format_loc(seen[2])}, which says security "
                        f"{seen[0]!r}; a shared link has one security mode"
                    ),
                )
            if name is not None:
                named = by_name.setdefault(name, (uri, loc))
                if named[0] != uri:
                    yield (
                        (*loc, "name"),
                        (
                            f"link name {name!r} is already used for {named[0]} at "
                            f"{format_loc(named[1])}"
                        ),
                    )


SinkChecker = Callable[[str, dict[str, Any]], None]
"""Checks a sink's ``type`` and ``options``; raises ``ValidationError`` or ``SinkLoadError``."""


def _sink_issues(data: dict[str, Any], check_sink: SinkChecker) -> Iterator[tuple[Loc, str]]:
    sinks = data.get("sinks")
    if not isinstance(sinks, list):
        return
    for i, item in enumerate(sinks):
        if not isinstance(item, dict) or not isinstance(item.get("type"), str):
            continue
        options = item.get("options") or {}
        if not isinstance(options, dict):
            continue
        try:
            check_sink(item["type"], options)
        except ValidationError as exc:
            yield from _issues_from_validation(exc, ("sinks", i, "options"))
        except SinkLoadError as exc:
            yield ("sinks", i, "type"), str(exc)


def load_config_text(
    text: str, source: str = "<config>", *, check_sink: SinkChecker | None = None
) -> Config:
    """Parse and validate YAML ``text``; raise ``ConfigError`` listing every problem.

    ``check_sink``, when given, also validates each sink's type and options (the plugin
    loader provides it), so those problems are reported with their lines too.
    """
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        problem = getattr(exc, "problem", None) or str(exc)
        issue = ConfigIssue(source, line, "(yaml)", f"not valid YAML: {problem}")
        raise ConfigError([issue]) from exc
    if data is None:
        data = {}
    if not isinstance(data, dict):
        issue = ConfigIssue(source, 1, "(top level)", "expected a mapping of sections")
        raise ConfigError([issue])
    lines = _Lines()
    if node is not None:
        lines.walk(node, ())
    found: list[tuple[Loc, str]] = [
        (loc, "duplicate key; the later value would silently win") for loc, _ in lines.duplicates
    ]
    config: Config | None = None
    try:
        config = Config.model_validate(data)
    except ValidationError as exc:
        found.extend(_issues_from_validation(exc, ()))
    found.extend(_cross_check(data))
    found.extend(_link_checks(data))
    if check_sink is not None:
        found.extend(_sink_issues(data, check_sink))
    if found or config is None:
        dup_lines = dict(lines.duplicates)
        issues = [
            ConfigIssue(source, dup_lines.get(loc) or lines.line(loc), format_loc(loc), message)
            for loc, message in found
        ]
        issues.sort(key=lambda issue: (issue.line or 0, issue.key_path))
        raise ConfigError(issues)
    return config


def load_config(path: Path, *, check_sink: SinkChecker | None = None) -> Config:
    """Read and validate the config file at ``path``; raise ``ConfigError`` naming its lines."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        issue = ConfigIssue(str(path), None, "(file)", f"cannot read: {exc.strerror}")
        raise ConfigError([issue]) from exc
    return load_config_text(text, str(path), check_sink=check_sink)
