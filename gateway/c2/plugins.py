"""Plugin discovery through entry points: sinks, processors and sources.

Groups: ``fischer_gateway.sinks``, ``fischer_gateway.processors``,
``fischer_gateway.sources``. Built-in plugins are registered under the same groups in our
own ``pyproject.toml``, so a third-party plugin installed as a package and one of ours take
the same single code path. Only the names a config uses are loaded; a name that cannot be
loaded fails at load time with a ``SinkLoadError`` naming the type, its distribution and
what is wrong.
"""

from __future__ import annotations

import builtins
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any, cast

from pydantic import BaseModel, ValidationError

from gateway.c2.sink import Sink, SinkClass
from gateway.errors import SinkLoadError, SinkOptionsInvalid
from gateway.events import declared_extensions

__all__ = [
    "GROUP",
    "PROCESSOR_GROUP",
    "SOURCE_GROUP",
    "Component",
    "SinkPlugin",
    "available",
    "build_sink",
    "check_component",
    "check_sink",
    "load_component",
    "load_plugin",
]

GROUP = "fischer_gateway.sinks"
PROCESSOR_GROUP = "fischer_gateway.processors"
SOURCE_GROUP = "fischer_gateway.sources"
_WHAT = {GROUP: "sink", PROCESSOR_GROUP: "processor", SOURCE_GROUP: "source"}
_REQUIRED = {
    GROUP: ("open", "send", "aclose"),
    PROCESSOR_GROUP: ("run",),
    SOURCE_GROUP: ("run",),
}


@dataclass(frozen=True, slots=True)
class Component:
    """A loaded plugin type of any group: its factory, options model and origin."""

    group: str
    type_name: str
    factory: Any
    model: builtins.type[BaseModel]
    distribution: str
    version: str


_components: dict[tuple[str, str], Component] = {}


def load_component(group: str, type_name: str) -> Component:
    """Import ``type_name`` of entry-point ``group``; check it has a model and ``run``."""
    cached = _components.get((group, type_name))
    if cached is not None:
        return cached
    what = _WHAT[group]
    matches = entry_points(group=group, name=type_name)
    if len(matches) != 1:
        known = ", ".join(sorted(ep.name for ep in entry_points(group=group))) or "none"
        problem = "unknown" if not matches else "ambiguous (several distributions provide it)"
        raise SinkLoadError(
            f"{problem} {what} type {type_name!r}; installed {what} types: {known}",
            sink=type_name,
        )
    (entry,) = matches
    dist = entry.dist.name if entry.dist else "unknown"
    version = entry.dist.version if entry.dist else "unknown"
    try:
        factory = entry.load()
    except Exception as exc:
        raise SinkLoadError(
            f"{what} type {type_name!r} from {dist} {version} failed to import "
            f"{entry.value}: {type(exc).__name__}: {exc}",
            sink=type_name,
        ) from exc
    model = getattr(factory, "config_model", None)
    if not (isinstance(model, type) and issubclass(model, BaseModel)):
        raise SinkLoadError(
            f"{what} type {type_name!r} from {dist} {version} has no pydantic 'config_model'",
            sink=type_name,
        )
    missing = [m for m in _REQUIRED[group] if not callable(getattr(factory, m, None))]
    if missing:
        raise SinkLoadError(
            f"{what} type {type_name!r} from {dist} {version} lacks {', '.join(missing)}",
            sink=type_name,
        )
    if group == PROCESSOR_GROUP:
        try:
            declared_extensions(factory)
        except ValueError as exc:
            raise SinkLoadError(
                f"{what} type {type_name!r} from {dist} {version}: {exc}", sink=type_name
            ) from None
    component = Component(group, type_name, factory, model, dist, version)
    _components[(group, type_name)] = component
    return component


def check_component(group: str, type_name: str, options: dict[str, Any]) -> BaseModel:
    """Load and validate; raise ``SinkLoadError`` or ``SinkOptionsInvalid``."""
    component = load_component(group, type_name)
    try:
        return component.model.model_validate(options)
    except ValidationError as exc:
        raise SinkOptionsInvalid(type_name, exc, component.model) from None


@dataclass(frozen=True, slots=True)
class SinkPlugin:
    """A loaded sink type: its factory and where it came from."""

    type: str
    factory: SinkClass
    distribution: str
    version: str

    def build(self, name: str, options: dict[str, Any]) -> Sink:
        """Validate ``options`` with the sink's model and construct it (no I/O yet).

        Raises pydantic's ``ValidationError`` for bad options.
        """
        config = self.factory.config_model.model_validate(options)
        return self.factory(name, config)


_cache: dict[str, SinkPlugin] = {}


def load_plugin(type_name: str) -> SinkPlugin:
    """Import the sink type ``type_name`` and check it honours the contract."""
    plugin = _cache.get(type_name)
    if plugin is None:
        component = load_component(GROUP, type_name)
        plugin = SinkPlugin(
            type_name, cast("SinkClass", component.factory), component.distribution,
            component.version,
        )  # fmt: skip
        _cache[type_name] = plugin
    return plugin


def check_sink(type_name: str, options: dict[str, Any]) -> None:
    """Load ``type_name`` and validate ``options``; the config loader's sink checker.

    Raises ``SinkLoadError`` for a type that cannot be loaded and ``SinkOptionsInvalid``
    (with pydantic's error and the options model) for options that do not validate.
    """
    model = load_plugin(type_name).factory.config_model
    try:
        model.model_validate(options)
    except ValidationError as exc:
        raise SinkOptionsInvalid(type_name, exc, model) from None


def build_sink(type_name: str, name: str, options: dict[str, Any]) -> Sink:
    """Load, validate and construct one configured sink."""
    return load_plugin(type_name).build(name, options)


def available() -> dict[str, str]:
    """Every installed sink type and the distribution providing it (nothing is imported)."""
    return {ep.name: (ep.dist.name if ep.dist else "unknown") for ep in entry_points(group=GROUP)}
