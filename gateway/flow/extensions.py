"""The extension point: event types a third-party processor declares and publishes.

A processor class declares its own event types in a class attribute, beside its
``config_model``::

    class WeatherFeed:
        config_model = WeatherConfig
        extension_events = {"acme.weather": Weather}   # type name -> pydantic model of data

and publishes them as ``gateway.events.Extension(type="acme.weather", data={...})``. Before such
an event reaches the bus, its processor's runner checks it (``ExtensionGate.admit``): the type
must be one the processor declared and ``data`` must validate against that type's model.
An event that fails is refused (``publish`` returns False), counted under the processor's name
in ``fg_extension_refused_total`` and logged at most every few seconds per processor; the
processor and the daemon carry on. An accepted event has ``publisher`` set to the
processor's configured name; the bus takes an ``Extension`` only from a publisher that
declared its type.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import structlog
from pydantic import BaseModel, ValidationError

from gateway.events import EXTENSION_TYPE_MAX, EXTENSION_TYPE_PATTERN, Extension
from gateway.ops.instruments import Instruments
from gateway.ops.logsetup import RateLimit

__all__ = ["ExtensionGate", "declared_extensions"]

log = structlog.get_logger(__name__)

_TYPE = re.compile(EXTENSION_TYPE_PATTERN)
#: A processor may declare at most this many types.
MAX_DECLARED = 64


def declared_extensions(factory: object) -> dict[str, type[BaseModel]]:
    """The ``extension_events`` a processor class (or instance) declares; {} when none.

    Raises ``ValueError`` saying what is wrong with a declaration that is not a mapping of
    valid type names to pydantic models.
    """
    declared = getattr(factory, "extension_events", None)
    if declared is None:
        return {}
    if not isinstance(declared, Mapping):
        raise ValueError(
            f"extension_events must map type names to pydantic models, got {declared!r}"
        )
    if len(declared) > MAX_DECLARED:
        raise ValueError(f"extension_events declares {len(declared)} types; at most {MAX_DECLARED}")
    types: dict[str, type[BaseModel]] = {}
    for name, model in declared.items():
        if not (
            isinstance(name, str) and len(name) <= EXTENSION_TYPE_MAX and _TYPE.fullmatch(name)
        ):
            raise ValueError(
                f"extension_events: {name!r} is not a type name: dot-separated lowercase "
                f"parts, a namespace first ('acme.weather'), at most {EXTENSION_TYPE_MAX} "
                "characters"
            )
        if not (isinstance(model, type) and issubclass(model, BaseModel)):
            raise ValueError(f"extension_events[{name!r}] must be a pydantic model, got {model!r}")
        types[name] = model
    return types


class ExtensionGate:
    """Checks one processor's ``Extension`` events against what it declared."""

    def __init__(
        self, publisher: str, declared: Mapping[str, type[BaseModel]], instruments: Instruments
    ) -> None:
        self.publisher = publisher
        self.declared = dict(declared)
        self._undeclared = instruments.extension_refused.labels(publisher, "undeclared")
        self._invalid = instruments.extension_refused.labels(publisher, "invalid")
        self._log_limit = RateLimit(interval_s=5.0)
        self.log = log.bind(processor=publisher)

    @property
    def types(self) -> frozenset[str]:
        """The type names this processor may publish."""
        return frozenset(self.declared)

    def admit(self, event: Extension) -> Extension | None:
        """``event`` stamped with its publisher, or None (counted, logged) if it is refused."""
        model = self.declared.get(event.type)
        if model is None:
            self._undeclared.inc()
            if self._log_limit.allow("undeclared"):
                self.log.error(
                    "extension_refused",
                    type=event.type,
                    reason="undeclared",
                    declared=sorted(self.declared),
                    refused=int(self._undeclared.value),
                )
            return None
        try:
            model.model_validate(event.data)
        except ValidationError as exc:
            self._invalid.inc()
            if self._log_limit.allow("invalid"):
                self.log.error(
                    "extension_refused",
                    type=event.type,
                    reason="invalid",
                    error=str(exc.errors(include_url=False, include_input=False))[:500],
                    refused=int(self._invalid.value),
                )
            return None
        if event.publisher == self.publisher:
            return event
        return event.model_copy(update={"publisher": self.publisher})
