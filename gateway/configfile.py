"""Loading the config file: YAML with line numbers, every problem reported at once.

``load_config`` reports every problem it finds, each as ``FILE:LINE key.path: what was
expected, what was found``, by raising one ``ConfigError``: pydantic's validation errors,
duplicate YAML keys, and the checks across items (duplicate sysids, routes naming sinks
that do not exist, links whose security needs a key that is not configured, listeners
beyond loopback that the config does not say it wants ...).

The file is input like any other, so reading it is bounded: at most ``MAX_CONFIG_BYTES``,
nesting at most ``MAX_DEPTH`` deep, at most ``MAX_ALIASES`` aliases and ``MAX_NODES`` nodes
once aliases are expanded (a 368-byte alias bomb expands to billions), each refused with
the line where the limit was passed. A boolean where a number belongs (``port: true``) and
a non-finite number (``.inf``, ``.nan``) are errors, not 1 and "never".
"""

from __future__ import annotations

import difflib
import math
import os
import stat
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from types import UnionType
from typing import Annotated, Any, Literal, TypeVar, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ValidationError

from gateway.config import Config
from gateway.errors import ConfigError, ConfigIssue, SinkLoadError, SinkOptionsInvalid

__all__ = [
    "MAX_ALIASES",
    "MAX_CONFIG_BYTES",
    "MAX_DEPTH",
    "MAX_NODES",
    "ExtraCheck",
    "Loc",
    "SinkChecker",
    "format_loc",
    "is_loopback_host",
    "load_config",
    "load_config_text",
    "load_model_text",
    "read_bounded_text",
    "validation_issues",
]

Loc = tuple[str | int, ...]
ModelT = TypeVar("ModelT", bound=BaseModel)

#: Largest config file read; a brigade's config is a few kilobytes.
MAX_CONFIG_BYTES = 1024 * 1024
#: Deepest nesting of mappings and sequences.
MAX_DEPTH = 32
#: Most aliases (``*name``) in one document.
MAX_ALIASES = 256
#: Most nodes once every alias is expanded.
MAX_NODES = 200_000


class _TooBig(Exception):
    """A limit of the loader was passed at ``line``."""

    def __init__(self, line: int, message: str) -> None:
        super().__init__(message)
        self.line = line
        self.message = message


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe loader with the nesting depth and alias count bounded while composing."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._aliases = 0

    def compose_node(self, parent: yaml.Node | None, index: int) -> yaml.Node | None:
        event = self.peek_event()  # type: ignore[no-untyped-call]
        line = event.start_mark.line + 1 if event.start_mark is not None else 0
        if isinstance(event, yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_ALIASES:
                raise _TooBig(line, f"more than {MAX_ALIASES} aliases in one document")
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise _TooBig(line, f"nested more than {MAX_DEPTH} levels deep")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def is_loopback_host(host: str) -> bool:
    """True for ``localhost``, 127.0.0.0/8 and ::1; False for wildcards and other names."""
    if host == "localhost":
        return True
    try:
        from ipaddress import ip_address

        return ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


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
        self.nodes = 0

    def walk(self, node: yaml.Node, loc: Loc) -> None:
        self.nodes += 1
        if self.nodes > MAX_NODES:
            # Report the top-level key being expanded: an aliased node's own mark points
            # back at its anchor, far from where the expansion happens.
            line = self.by_loc.get(loc[:1], node.start_mark.line + 1)
            where = f"'{loc[0]}'" if loc else "the document"
            raise _TooBig(
                line, f"{where} expands to more than {MAX_NODES} nodes (aliases of aliases?)"
            )
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


def _model_at(model: type[BaseModel], loc: Loc) -> type[BaseModel] | None:
    """The model class that validates the mapping at ``loc`` below ``model``, if one does."""
    annotation: object = model
    for part in loc:
        annotation = _child_type(annotation, part)
    alternatives = _unwrap(annotation)
    if len(alternatives) == 1 and isinstance(alternatives[0], type):
        kind = alternatives[0]
        if issubclass(kind, BaseModel):
            return kind
    return None


def _unknown_key(key: str, parent: type[BaseModel] | None) -> str:
    if parent is None:
        return f"unknown key '{key}' (a typo?); expected one of the documented keys"
    known = sorted(parent.model_fields)
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    hint = f"did you mean '{close[0]}'?" if close else f"expected one of: {', '.join(known)}"
    return f"unknown key '{key}'; {hint}"


def _missing_key(key: str, parent: type[BaseModel] | None) -> str:
    field = parent.model_fields.get(key) if parent is not None else None
    message = f"missing required key '{key}'"
    if field is not None:
        choices = [
            str(arg)
            for alt in _unwrap(field.annotation)
            if get_origin(alt) is Literal
            for arg in get_args(alt)
        ]
        if choices:
            message += f": one of {', '.join(choices)}"
        if field.description:
            message += f" ({field.description.rstrip('.')})"
    return message


def validation_issues(
    exc: ValidationError, prefix: Loc, model: type[BaseModel] | None = None
) -> Iterator[tuple[Loc, str]]:
    """pydantic's errors as ``(loc, message)`` under ``prefix``, worded for operators."""
    return _issues_from_validation(exc, prefix, model)


def _issues_from_validation(
    exc: ValidationError, prefix: Loc, model: type[BaseModel] | None = None
) -> Iterator[tuple[Loc, str]]:
    errors = exc.errors()
    inner = {tuple(e["loc"][:n]) for e in errors for n in range(len(e["loc"]))}
    for error in errors:
        if error["type"] == "too_short" and tuple(error["loc"]) in inner:
            # pydantic also reports a list as too short when one of its items failed.
            continue
        loc: Loc = (*prefix, *error["loc"])
        message = error["msg"].removeprefix("Value error, ")
        parent = _model_at(model, error["loc"][:-1]) if model is not None else None
        if error["type"] == "extra_forbidden":
            message = _unknown_key(str(loc[-1]), parent)
        elif error["type"] == "missing":
            message = _missing_key(str(loc[-1]), parent)
        elif "found" not in message and not isinstance(error.get("input"), dict | list):
            # A whole mapping or list is no help after the message; a scalar is.
            message = f"{message}, found {_found(error.get('input'))}"
        yield loc, message


def _not_one_of(what: str, name: object, known: Iterable[object]) -> str:
    names = sorted(str(k) for k in known)
    close = difflib.get_close_matches(str(name), names, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}?" if close else f"configured: {', '.join(names) or 'none'}"
    return f"no {what} named {name!r}; {hint}"


def _cross_check(data: dict[str, Any]) -> Iterator[tuple[Loc, str]]:
    """Checks across items, made on the raw data so they report even if other items fail."""
    if not data.get("airframes") and not data.get("sources"):
        yield (
            (),
            "nothing to do: no airframes and no sources are configured "
            "(config/example.yaml shows both)",
        )
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
    for section in ("sources", "processors"):
        items = data.get(section)
        names: dict[object, int] = {}
        for i, item in enumerate(items if isinstance(items, list) else ()):
            if not isinstance(item, dict):
                continue
            name = item.get("name", "cot" if section == "sources" else None)
            if name is None:
                continue
            if name in names:
                yield (
                    (section, i, "name"),
                    f"duplicate name {name!r}, already used by {section}[{names[name]}]",
                )
            else:
                names[name] = i
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
                    yield ("routes", i, "sinks", j), _not_one_of("sink", name, sink_names)
            for j, name in enumerate(route.get("airframes") or ()):
                if name != "*" and name not in ids:
                    yield ("routes", i, "airframes", j), _not_one_of("airframe", name, ids)


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
"""Checks a sink's ``type`` and ``options``; raises ``SinkOptionsInvalid`` or ``SinkLoadError``."""


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
        except SinkOptionsInvalid as exc:
            if isinstance(exc.validation, ValidationError):
                model = exc.model if issubclass(exc.model, BaseModel) else None
                yield from _issues_from_validation(exc.validation, ("sinks", i, "options"), model)
        except SinkLoadError as exc:
            yield ("sinks", i, "type"), str(exc)


ExtraCheck = Callable[[dict[str, Any], Config | None], Iterable[tuple[Loc, str, bool]]]
"""More checks on the raw data and the model (None if it failed): ``(loc, message, is_error)``."""


def load_config_text(
    text: str,
    source: str = "<config>",
    *,
    check_sink: SinkChecker | None = None,
    extra: ExtraCheck | None = None,
    warnings: list[ConfigIssue] | None = None,
) -> Config:
    """Parse and validate YAML ``text``; raise ``ConfigError`` listing every problem.

    ``check_sink``, when given, also validates each sink's type and options (the plugin
    loader provides it), so those problems are reported with their lines too. ``extra``
    adds checks (``gateway.configcheck``: key files, devices, sink construction); what it
    reports as not an error goes, with its line, to ``warnings``.
    """
    data, lines = _parse_yaml(text, source)
    config, found = _validate(data, lines, Config)
    found.extend(_cross_check(data))
    found.extend(_link_checks(data))
    found.extend(_bind_checks(data))
    if check_sink is not None:
        found.extend(_sink_issues(data, check_sink))
    if extra is not None:
        for loc, message, is_error in extra(data, None if found else config):
            if is_error:
                found.append((loc, message))
            elif warnings is not None:
                warnings.append(ConfigIssue(source, lines.line(loc), format_loc(loc), message))
    if found or config is None:
        raise _config_error(found, lines, source)
    return config


def load_config(
    path: Path,
    *,
    check_sink: SinkChecker | None = None,
    extra: ExtraCheck | None = None,
    warnings: list[ConfigIssue] | None = None,
) -> Config:
    """Read and validate the config file at ``path``; raise ``ConfigError`` naming its lines.

    Refuses anything but a regular file of at most ``MAX_CONFIG_BYTES`` before reading it.
    ``check_sink``, ``extra`` and ``warnings`` are as for ``load_config_text``.
    """
    text = read_bounded_text(path)
    return load_config_text(text, str(path), check_sink=check_sink, extra=extra, warnings=warnings)


def _parse_yaml(text: str, source: str) -> tuple[dict[str, Any], _Lines]:
    """The top-level mapping of YAML ``text`` and the lines of its keys; ``ConfigError`` if
    it is too big, not YAML or not a mapping."""
    if len(text) > MAX_CONFIG_BYTES:
        message = f"{len(text)} characters; a config file is at most {MAX_CONFIG_BYTES}"
        raise ConfigError([ConfigIssue(source, None, "(file)", message)])
    lines = _Lines()
    loader: _BoundedLoader | None = None
    try:
        loader = _BoundedLoader(text)
        node = loader.get_single_node()
        if node is not None:
            lines.walk(node, ())
        data = loader.construct_document(node) if node is not None else None
    except _TooBig as exc:
        raise ConfigError([ConfigIssue(source, exc.line, "(yaml)", exc.message)]) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        problem = getattr(exc, "problem", None) or str(exc)
        issue = ConfigIssue(source, line, "(yaml)", f"not valid YAML: {problem}")
        raise ConfigError([issue]) from exc
    finally:
        if loader is not None:
            loader.dispose()
    if data is None:
        data = {}
    if not isinstance(data, dict):
        issue = ConfigIssue(source, 1, "(top level)", "expected a mapping of sections")
        raise ConfigError([issue])
    return data, lines


def load_model_text(
    text: str,
    source: str,
    model: type[ModelT],
    *,
    checks: Callable[[dict[str, Any]], Iterable[tuple[Loc, str]]] | None = None,
) -> ModelT:
    """Parse YAML ``text`` into ``model`` with the config file's bounds and error reports.

    For YAML files other than the config (simulator scenarios ...): every problem, each
    naming ``source``, its line and key path, in one ``ConfigError``. ``checks`` adds checks
    across items on the raw data, reported the same way.
    """
    data, lines = _parse_yaml(text, source)
    value, found = _validate(data, lines, model)
    if checks is not None:
        found.extend(checks(data))
    if found or value is None:
        raise _config_error(found, lines, source)
    return value


def _validate(
    data: dict[str, Any], lines: _Lines, model: type[ModelT]
) -> tuple[ModelT | None, list[tuple[Loc, str]]]:
    """``model`` from parsed YAML (None if invalid) and the problems found so far."""
    found: list[tuple[Loc, str]] = [
        (loc, "duplicate key; the later value would silently win") for loc, _ in lines.duplicates
    ]
    value: ModelT | None = None
    try:
        value = model.model_validate(data)
    except ValidationError as exc:
        found.extend(_issues_from_validation(exc, (), model))
    reported = {loc for loc, _ in found}
    found.extend(issue for issue in _number_checks(data, model, ()) if issue[0] not in reported)
    return value, found


def _config_error(found: list[tuple[Loc, str]], lines: _Lines, source: str) -> ConfigError:
    """Every problem, each with its line (a duplicate key's own line), sorted by line."""
    dup_lines = dict(lines.duplicates)
    issues = [
        ConfigIssue(source, dup_lines.get(loc) or lines.line(loc), format_loc(loc), message)
        for loc, message in found
    ]
    issues.sort(key=lambda issue: (issue.line or 0, issue.key_path))
    return ConfigError(issues)


def read_bounded_text(path: Path) -> str:
    """The UTF-8 text of the regular file at ``path``, at most ``MAX_CONFIG_BYTES``.

    Refuses anything else before reading it, with a ``ConfigError`` naming the file.
    """
    source = str(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        issue = ConfigIssue(source, None, "(file)", f"cannot read: {exc.strerror}")
        raise ConfigError([issue]) from exc
    try:
        info = os.fstat(fd)
        problem = None
        if stat.S_ISDIR(info.st_mode):
            problem = "a directory, not a config file"
        elif not stat.S_ISREG(info.st_mode):
            problem = "not a regular file"
        elif info.st_size > MAX_CONFIG_BYTES:
            problem = f"{info.st_size} bytes; a config file is at most {MAX_CONFIG_BYTES}"
        if problem is not None:
            raise ConfigError([ConfigIssue(source, None, "(file)", problem)])
        try:
            raw = os.read(fd, MAX_CONFIG_BYTES + 1)
        except OSError as exc:
            issue = ConfigIssue(source, None, "(file)", f"cannot read: {exc.strerror}")
            raise ConfigError([issue]) from exc
    finally:
        os.close(fd)
    if len(raw) > MAX_CONFIG_BYTES:
        message = f"more than {MAX_CONFIG_BYTES} bytes; a config file is at most that"
        raise ConfigError([ConfigIssue(source, None, "(file)", message)])
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        message = f"not UTF-8 text (byte {exc.start})"
        raise ConfigError([ConfigIssue(source, None, "(file)", message)]) from exc


def _number_checks(raw: object, expected: object, loc: Loc) -> Iterator[tuple[Loc, str]]:
    """Non-finite numbers anywhere; booleans where the model's type is a number.

    ``expected`` is the annotation the models give this position (walked from ``Config``),
    so the check works even when validation failed elsewhere in the file.
    """
    if isinstance(raw, bool):
        if _is_number_type(expected):
            yield loc, f"expected a number, found the boolean {raw!r}"
    elif isinstance(raw, float):
        if not math.isfinite(raw):
            yield loc, f"expected a finite number, found {raw!r}"
    elif isinstance(raw, dict):
        for key, value in raw.items():
            yield from _number_checks(value, _child_type(expected, key), (*loc, str(key)))
    elif isinstance(raw, list):
        item = _child_type(expected, 0)
        for index, value in enumerate(raw):
            yield from _number_checks(value, item, (*loc, index))


def _unwrap(annotation: object) -> list[object]:
    """The alternatives of an annotation, without Annotated, Optional and None."""
    origin = get_origin(annotation)
    if origin is Annotated:
        return _unwrap(get_args(annotation)[0])
    if origin in (Union, UnionType):
        return [alt for arg in get_args(annotation) for alt in _unwrap(arg)]
    return [] if annotation is type(None) else [annotation]


def _is_number_type(annotation: object) -> bool:
    alternatives = _unwrap(annotation)
    return bool(alternatives) and all(alt in (int, float) for alt in alternatives)


def _child_type(annotation: object, key: object) -> object:
    """The annotation of the value under ``key`` of a value annotated ``annotation``."""
    alternatives = _unwrap(annotation)
    if len(alternatives) != 1:
        return None
    (kind,) = alternatives
    if isinstance(kind, type) and issubclass(kind, BaseModel):
        field = kind.model_fields.get(key) if isinstance(key, str) else None
        return None if field is None else field.annotation
    origin, args = get_origin(kind), get_args(kind)
    if origin in (tuple, list) and args:
        return args[0]
    if origin is dict and len(args) == 2:
        return args[1]
    return None


def _bind_checks(data: dict[str, Any]) -> Iterator[tuple[Loc, str]]:
    """Plain-MAVLink and status listeners beyond loopback only where the config says so."""
    health = data.get("health")
    if isinstance(health, dict) and health.get("enabled", True):
        host = health.get("host", "127.0.0.1")
        if (
            isinstance(host, str)
            and not is_loopback_host(host)
            and not health.get("allow_non_loopback")
        ):
            yield (
                ("health", "host"),
                f"{host!r} is beyond loopback: /status and /metrics describe the fleet; "
                "add health.allow_non_loopback: true if that is intended",
            )
    airframes = data.get("airframes")
    for i, airframe in enumerate(airframes if isinstance(airframes, list) else ()):
        if not isinstance(airframe, dict):
            continue
        passthrough = _mapping_or_empty(airframe.get("passthrough"))
        host = _uri_host(passthrough.get("uri"))
        exposed = host is not None and not is_loopback_host(host)
        if exposed and not passthrough.get("allow_non_loopback"):
            yield (
                ("airframes", i, "passthrough", "uri"),
                f"{host!r} is beyond loopback and the passthrough is plain MAVLink (anyone "
                "who reaches it reads the airframe's telemetry); add "
                "allow_non_loopback: true to the passthrough if that is intended",
            )
        links = airframe.get("links")
        for j, link in enumerate(links if isinstance(links, list) else ()):
            if not isinstance(link, dict) or link.get("security") != "unsecured":
                continue
            uri = link.get("uri")
            host = _uri_host(uri)
            listens = isinstance(uri, str) and (
                (uri.startswith("udp://") and "mode=connect" not in uri) or "mode=listen" in uri
            )
            exposed = host is not None and listens and not is_loopback_host(host)
            if exposed and not link.get("allow_non_loopback"):
                yield (
                    ("airframes", i, "links", j, "uri"),
                    f"an unsecured link listening on {host!r} (beyond loopback) accepts "
                    "anyone's frames; add allow_non_loopback: true to this link if that "
                    "is intended",
                )


def _uri_host(uri: object) -> str | None:
    if not isinstance(uri, str) or not uri.startswith(("udp://", "tcp://")):
        return None
    try:
        from urllib.parse import urlsplit

        return urlsplit(uri).hostname
    except ValueError:
        return None


def _mapping_or_empty(value: object) -> dict[str, Any]:
    return value if isinstance(value, dict) else {}
