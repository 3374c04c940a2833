"""The gateway's configuration: pydantic models of the YAML, and loading that names lines.

Everything is validated once, at load. ``load_config`` reports every problem it finds, each
as ``FILE:LINE key.path: what was expected, what was found``, by raising one ``ConfigError``.
Secrets never live in this file: options that need one take a path to it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import parse_qsl, urlsplit

import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    ValidationError,
    WithJsonSchema,
)

from gateway.errors import ConfigError, ConfigIssue, SinkLoadError
from gateway.events import EventKind

__all__ = [
    "AirframeConfig",
    "Config",
    "Endpoint",
    "GatewayConfig",
    "HealthConfig",
    "LinkConfig",
    "RouteConfig",
    "SinkEntry",
    "format_loc",
    "load_config",
    "load_config_text",
    "parse_endpoint",
]

_FROZEN = ConfigDict(frozen=True, extra="forbid")
_ID = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"


@dataclass(frozen=True, slots=True)
class Endpoint:
    """A parsed link URI: ``udp://``, ``tcp://`` or ``serial://``, listening or connecting."""

    scheme: Literal["udp", "tcp", "serial"]
    mode: Literal["listen", "connect"]
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 57600
    text: str = field(default="", compare=False)

    def __str__(self) -> str:
        return self.text


_MODES: dict[str, tuple[str, ...]] = {"udp": ("listen", "connect"), "tcp": ("connect", "listen")}


def parse_endpoint(value: object) -> Endpoint:
    """Parse a link URI; raise ``ValueError`` saying what was expected.

    ``udp://HOST:PORT`` listens (``?mode=connect`` sends to that address), ``tcp://HOST:PORT``
    connects (``?mode=listen`` serves), ``serial:///dev/ttyX?baud=57600`` opens a device.
    """
    if isinstance(value, Endpoint):
        return value
    if not isinstance(value, str):
        raise ValueError(f"expected a link URI string, found {type(value).__name__}")
    parts = urlsplit(value)
    scheme = parts.scheme
    try:
        params = dict(parse_qsl(parts.query, strict_parsing=bool(parts.query)))
    except ValueError as exc:
        raise ValueError(f"expected key=value query parameters, found {parts.query!r}") from exc
    if scheme == "serial":
        device = parts.path
        if not device.startswith("/"):
            raise ValueError(f"expected serial:///dev/DEVICE, found {value!r}")
        unknown = set(params) - {"baud"}
        if unknown:
            raise ValueError(f"expected only 'baud' as a serial parameter, found {sorted(unknown)}")
        baud_text = params.get("baud", "57600")
        if not baud_text.isdigit() or not 50 <= int(baud_text) <= 4_000_000:
            raise ValueError(f"expected baud between 50 and 4000000, found {baud_text!r}")
        return Endpoint("serial", "connect", device=device, baud=int(baud_text), text=value)
    if scheme not in _MODES:
        raise ValueError(f"expected udp://, tcp:// or serial://, found {value!r}")
    unknown = set(params) - {"mode"}
    if unknown:
        raise ValueError(f"expected only 'mode' as a {scheme} parameter, found {sorted(unknown)}")
    mode = params.get("mode", _MODES[scheme][0])
    if mode not in ("listen", "connect"):
        raise ValueError(f"expected mode=listen or mode=connect, found mode={mode!r}")
    try:
        host, port = parts.hostname, parts.port
    except ValueError as exc:
        raise ValueError(
            f"expected {scheme}://HOST:PORT with a port 1-65535, found {value!r}"
        ) from exc
    if not host or not port or parts.path not in ("", "/"):
        raise ValueError(f"expected {scheme}://HOST:PORT, found {value!r}")
    return Endpoint(scheme, mode, host=host, port=port, text=value)  # type: ignore[arg-type]


EndpointField = Annotated[
    Endpoint,
    BeforeValidator(parse_endpoint),
    PlainSerializer(str, return_type=str),
    WithJsonSchema(
        {
            "type": "string",
            "pattern": r"^(udp|tcp|serial)://",
            "description": "udp://HOST:PORT[?mode=listen|connect], tcp://HOST:PORT"
            "[?mode=connect|listen], serial:///dev/DEVICE[?baud=N]",
        }
    ),
]


class LinkConfig(BaseModel):
    """One transport to an airframe."""

    model_config = _FROZEN

    uri: EndpointField
    name: str | None = Field(default=None, pattern=_ID, description="Defaults to the URI.")
    priority: int = Field(default=0, ge=0, le=100, description="Lower is preferred.")
    max_frame_bytes: int = Field(default=2048, ge=64, le=65535)
    reconnect_initial_s: float = Field(default=0.5, gt=0)
    reconnect_max_s: float = Field(default=30.0, gt=0)

    @property
    def label(self) -> str:
        """The name shown in metrics and logs."""
        return self.name or str(self.uri)


class AirframeConfig(BaseModel):
    """One airframe of the fleet."""

    model_config = _FROZEN

    id: str = Field(pattern=_ID)
    sysid: int = Field(ge=1, le=255, description="MAVLink system id.")
    links: tuple[LinkConfig, ...] = Field(min_length=1)
    link_timeout_s: float = Field(default=3.0, gt=0)


class SinkEntry(BaseModel):
    """One configured output sink: its type (an entry point name) and delivery settings."""

    model_config = _FROZEN

    name: str = Field(pattern=_ID)
    type: str = Field(pattern=r"^[a-z][a-z0-9_]*$")
    options: dict[str, Any] = Field(default_factory=dict)
    queue_max: int = Field(default=10_000, ge=1, description="Durable events held in memory.")
    batch_max: int = Field(default=100, ge=1, le=10_000)
    send_timeout_s: float = Field(default=5.0, gt=0)
    retry_initial_s: float = Field(default=0.5, gt=0)
    retry_max_s: float = Field(default=30.0, gt=0)


class RouteConfig(BaseModel):
    """Which events go to which sinks. An omitted filter matches everything."""

    model_config = _FROZEN

    sinks: tuple[str, ...] = Field(min_length=1)
    kinds: tuple[EventKind, ...] | None = None
    airframes: tuple[str, ...] | None = None
    classes: tuple[str, ...] | None = None
    max_rate_hz: float | None = Field(
        default=None,
        gt=0,
        description="Per airframe, for latest-wins kinds only; durable kinds are never thinned.",
    )


class HealthConfig(BaseModel):
    """The HTTP health and metrics endpoint."""

    model_config = _FROZEN

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = Field(default=8765, ge=0, le=65535)


class GatewayConfig(BaseModel):
    """Settings of the daemon itself."""

    model_config = _FROZEN

    node_id: str = Field(default="fischer-gateway", pattern=_ID)
    shutdown_deadline_s: float = Field(default=5.0, gt=0, le=300)
    log_level: Literal["debug", "info", "warning", "error"] = "info"


class Config(BaseModel):
    """The whole configuration file."""

    model_config = _FROZEN

    gateway: GatewayConfig = GatewayConfig()
    health: HealthConfig = HealthConfig()
    airframes: tuple[AirframeConfig, ...] = ()
    sinks: tuple[SinkEntry, ...] = ()
    routes: tuple[RouteConfig, ...] = ()


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
    for error in exc.errors():
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
