"""Checks of a config against the node it runs on, reported in the same pass as the schema's.

``NodeCheck`` is the ``extra`` check of ``load_config``: with ``environment=True`` (``run``,
and ``check-config`` by default) it reads every key file and credential the config names,
looks for serial devices and DEM directories, builds every sink (so a sink whose files are
missing, whose constructor is wrong, or whose ``kinds`` are not ``EventKind`` members is a
config error with its line, not a traceback at start) and checks each route's kinds against
the sinks it names. With ``environment=False`` (``check-config --no-environment``, for a
config checked away from the node) none of that is touched. What the daemon survives (a
serial device not plugged in yet, a DEM directory not there) is a warning, not an error.
"""

from __future__ import annotations

import os
from collections.abc import Generator, Iterator, Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from gateway.app import dem_sources
from gateway.c2.plugins import (
    PROCESSOR_GROUP,
    SOURCE_GROUP,
    check_component,
    load_component,
    load_plugin,
)
from gateway.c2.sink import Sink
from gateway.clock import utc_now
from gateway.config import Config
from gateway.configfile import Loc, validation_issues
from gateway.domain.terrain import check_sources
from gateway.errors import ConfigError, SinkLoadError, SinkOptionsInvalid
from gateway.events import EventKind
from gateway.fleet.security.keys import read_credential, read_key_file

__all__ = ["NodeCheck"]

Finding = tuple[Loc, str, bool]
_KINDS = frozenset(kind.value for kind in EventKind)
#: The validation context of sink options checked on the node itself.
_ON_NODE = {"environment": True}


class NodeCheck:
    """The node-side checks of one config load; keeps the sinks it built for ``Gateway``."""

    def __init__(self, *, environment: bool, env: Mapping[str, str] | None = None) -> None:
        self.environment = environment
        self.env = os.environ if env is None else env
        self.sinks: dict[str, Sink] = {}

    def __call__(self, data: dict[str, Any], config: Config | None) -> Iterator[Finding]:
        yield from _components(data, build=self.environment)
        if not self.environment:
            return
        yield from self._keys(data)
        yield from self._devices(data)
        if config is not None:
            for index, problem in check_sources(dem_sources(config)):
                yield ("terrain", "sources", index), problem, False
        kinds = yield from self._sinks(data)
        yield from self._routes(data, kinds)

    def _keys(self, data: dict[str, Any]) -> Iterator[Finding]:
        tunnel = _mapping(data.get("tunnel"))
        key_file = tunnel.get("master_key_file")
        if isinstance(key_file, str):
            yield from _key_problem(("tunnel", "master_key_file"), Path(key_file), exact=False)
        credential = tunnel.get("master_key_credential")
        if isinstance(credential, str):
            loc: Loc = ("tunnel", "master_key_credential")
            if not self.env.get("CREDENTIALS_DIRECTORY"):
                yield (
                    loc,
                    f"credential {credential!r} not checked: CREDENTIALS_DIRECTORY is not set "
                    "(it exists only under systemd, with LoadCredential=)",
                    False,
                )
            else:
                try:
                    read_credential(credential, self.env)
                except ConfigError as exc:
                    yield loc, "; ".join(issue.message for issue in exc.issues), True
        airframes = _items(data.get("airframes"))
        # Each key file is read once: its problem reported, its bytes kept for the comparison.
        signing_keys: list[tuple[str, bytes | None]] = []
        for i, airframe in enumerate(airframes):
            key_file = _mapping(airframe.get("signing")).get("key_file")
            key = None
            if isinstance(key_file, str):
                loc = ("airframes", i, "signing", "key_file")
                key, found = _read_key(loc, Path(key_file))
                yield from found
            signing_keys.append((str(airframe.get("id", i)), key))
        for i, airframe in enumerate(airframes):
            gcs_key_file = _mapping(airframe.get("passthrough")).get("key_file")
            if not isinstance(gcs_key_file, str):
                continue
            loc = ("airframes", i, "passthrough", "key_file")
            gcs_key, found = _read_key(loc, Path(gcs_key_file))
            yield from found
            for j, (other, key) in enumerate(signing_keys):
                if gcs_key is not None and gcs_key == key:
                    yield _same_key(loc, None if j == i else other)

    def _devices(self, data: dict[str, Any]) -> Iterator[Finding]:
        for i, airframe in enumerate(_items(data.get("airframes"))):
            for j, link in enumerate(_items(airframe.get("links"))):
                uri = link.get("uri")
                if isinstance(uri, str) and uri.startswith("serial://"):
                    device = uri.removeprefix("serial://").split("?", 1)[0]
                    if not os.path.exists(device):
                        yield (
                            ("airframes", i, "links", j, "uri"),
                            f"{device} does not exist now; the link will wait for it",
                            False,
                        )

    def _sinks(
        self, data: dict[str, Any]
    ) -> Generator[Finding, None, dict[str, frozenset[EventKind]]]:
        """Build every sink whose type and options are valid; return each one's kinds."""
        kinds: dict[str, frozenset[EventKind]] = {}
        for i, entry in enumerate(_items(data.get("sinks"))):
            name, type_name = entry.get("name"), entry.get("type")
            options = entry.get("options") or {}
            if not (isinstance(name, str) and isinstance(type_name, str)):
                continue
            if not isinstance(options, dict):
                continue
            try:
                plugin = load_plugin(type_name)
                plugin.factory.config_model.model_validate(options)
            except (ValidationError, SinkLoadError):
                continue  # reported by the schema pass, with the option's own line
            try:
                # Options validated again with the node at hand: a sink's validators may
                # then check its files (``info.context["environment"]``).
                config = plugin.factory.config_model.model_validate(options, context=_ON_NODE)
            except ValidationError as exc:
                for loc, message in validation_issues(exc, ("sinks", i, "options")):
                    yield loc, message, True
                continue
            where = f"sink type {type_name!r} from {plugin.distribution} {plugin.version}"
            try:
                sink = plugin.factory(name, config)
            except TypeError as exc:
                yield (
                    ("sinks", i, "type"),
                    f"{where} cannot be built as factory(name, config): {exc}",
                    True,
                )
                continue
            except (OSError, ValueError) as exc:
                yield ("sinks", i, "options"), f"{where} cannot be built: {exc}", True
                continue
            sink_kinds = getattr(sink, "kinds", None)
            if not isinstance(sink_kinds, set | frozenset) or not all(
                isinstance(kind, EventKind) for kind in sink_kinds
            ):
                yield (
                    ("sinks", i, "type"),
                    f"{where}: its 'kinds' must be a set of EventKind members, found "
                    f"{sink_kinds!r:.80}",
                    True,
                )
                continue
            self.sinks[name] = sink
            kinds[name] = frozenset(sink_kinds)
            # A sink may say what on this node it will wait for (a device, a program).
            notes = getattr(sink, "environment_warnings", None)
            for note in notes() if callable(notes) else ():
                yield ("sinks", i, "options"), f"sink {name!r}: {note}", False
        return kinds

    def _routes(
        self, data: dict[str, Any], kinds: Mapping[str, frozenset[EventKind]]
    ) -> Iterator[Finding]:
        for i, route in enumerate(_items(data.get("routes"))):
            wanted = route.get("kinds")
            if not isinstance(wanted, list):
                continue
            for name in route.get("sinks") or ():
                accepted = kinds.get(name) if isinstance(name, str) else None
                if accepted is None:
                    continue
                for j, kind in enumerate(wanted):
                    if isinstance(kind, str) and kind in _KINDS and EventKind(kind) not in accepted:
                        yield (
                            ("routes", i, "kinds", j),
                            f"sink {name!r} does not accept {kind!r}; it accepts "
                            f"{sorted(k.value for k in accepted)}",
                            True,
                        )


def _components(data: dict[str, Any], *, build: bool) -> Iterator[Finding]:
    """Sources' and processors' types and options; with ``build``, each is constructed too."""
    for i, entry in enumerate(_items(data.get("sources"))):
        type_name, name = entry.get("type", "cot"), entry.get("name", "cot")
        if not isinstance(type_name, str):
            continue
        options = {k: v for k, v in entry.items() if k not in ("name", "type")}
        loc: Loc = ("sources", i)
        yield from _component(SOURCE_GROUP, type_name, str(name), options, loc, build=build)
    airframes = sorted(str(a.get("id")) for a in _items(data.get("airframes")))
    for i, entry in enumerate(_items(data.get("processors"))):
        type_name, options = entry.get("type"), entry.get("options") or {}
        if isinstance(type_name, str) and isinstance(options, dict):
            loc = ("processors", i, "options")
            name = str(entry.get("name", type_name))
            yield from _component(PROCESSOR_GROUP, type_name, name, options, loc, build=build)
            # A fence for a mistyped airframe id would leave the real one unfenced.
            for key in _mapping(options.get("airframe_geofences")) if type_name == "orders" else ():
                if str(key) not in airframes:
                    known = ", ".join(airframes) or "none"
                    message = f"{key!r} is not an airframe of this config (airframes: {known})"
                    yield (*loc, "airframe_geofences", key), message, True


def _component(
    group: str,
    type_name: str,
    name: str,
    options: dict[str, Any],
    loc: Loc,
    *,
    build: bool,
) -> Iterator[Finding]:
    what = "source" if group == SOURCE_GROUP else "processor"
    try:
        config = check_component(group, type_name, options)
    except SinkOptionsInvalid as exc:
        if isinstance(exc.validation, ValidationError):
            model = exc.model if issubclass(exc.model, BaseModel) else None
            for where, message in validation_issues(exc.validation, loc, model):
                yield where, message, True
        return
    except SinkLoadError as exc:
        yield (*loc[:2], "type"), str(exc), True
        return
    if not build:
        return
    component = load_component(group, type_name)
    try:
        # Validated again with the node at hand: its validators may then check their files
        # and name the key that holds a bad one (as for sinks).
        config = component.model.model_validate(options, context=_ON_NODE)
    except ValidationError as exc:
        for where, message in validation_issues(exc, loc, component.model):
            yield where, message, True
        return
    # As the daemon will: a constructor that fails is a config error on this line.
    factory = component.factory
    try:
        if group == SOURCE_GROUP:
            factory(name, config, lambda _event: None, clock=utc_now)
        else:
            factory(name, config)
    except (TypeError, ValueError, OSError) as exc:
        yield (*loc[:2], "type"), f"{what} type {type_name!r} cannot be built: {exc}", True


def _key_problem(loc: Loc, path: Path, *, exact: bool) -> Iterator[Finding]:
    yield from _read_key(loc, path, exact=exact)[1]


def _read_key(loc: Loc, path: Path, *, exact: bool = True) -> tuple[bytes | None, list[Finding]]:
    """The key and no finding, or None and what is wrong with its file."""
    try:
        return read_key_file(path, exact=exact), []
    except ConfigError as exc:
        return None, [(loc, f"{path}: " + "; ".join(i.message for i in exc.issues), True)]


def _same_key(loc: Loc, other: str | None) -> Finding:
    """A ground station holding an airframe's signing key could command it around the policy.

    ``other`` names the airframe whose key it is when that is not the passthrough's own.
    """
    whose = "the airframe's" if other is None else f"airframe {other}'s"
    return (
        loc,
        f"the ground station's key is {whose} signing key: with it a ground "
        "station could sign commands to that airframe directly, around the gateway's "
        "command policy; give it a key of its own",
        True,
    )


def _mapping(value: object) -> dict[str, Any]:
    return value if isinstance(value, dict) else {}


def _items(value: object) -> list[dict[str, Any]]:
    return (
        [item if isinstance(item, dict) else {} for item in value]
        if isinstance(value, list)
        else []
    )
