"""The extension point: event types a third-party processor declares and publishes.

A processor class declares its own event types in a class attribute, beside its
``config_model``::

    class WeatherFeed:
        config_model = WeatherConfig
        extension_events = {"acme.weather": Weather}   # type name -> pydantic model of data

and publishes them as ``gateway.events.Extension(type="acme.weather", data={...})``
(``gateway.events.declared_extensions`` reads the declaration). Before such an event reaches
the bus, its processor's runner checks it (``ExtensionGate.admit``): the type must be one the
processor declared and ``data`` must validate against that type's model.
An event that fails is refused (``publish`` returns False), counted under the processor's name
in ``fg_extension_refused_total`` and logged at most every few seconds per processor; the
processor and the daemon carry on. An accepted event has ``publisher`` set to the
processor's configured name; the bus takes an ``Extension`` only from a publisher that
declared its type.
"""

from __future__ import annotations

from collections.abc import Mapping

import structlog
from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticSerializationError

from gateway.events import Extension
from gateway.ops.instruments import Instruments
from gateway.ops.logsetup import RateLimit

__all__ = ["ExtensionGate"]

log = structlog.get_logger(__name__)


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
                    type=event.type[:64],
                    reason="undeclared",
                    declared=sorted(self.declared),
                    refused=int(self._undeclared.value),
                )
            return None
        try:
            # The whole event as the spool and the sinks will see it: through JSON and back,
            # so an event built past its own checks (``model_construct``), a number JSON cannot
            # hold, data nested past any limit or past the size limit, is refused here and
            # never reaches the bus, then its model on the data.
            stamped = event.model_copy(update={"publisher": self.publisher})
            checked = Extension.model_validate_json(stamped.model_dump_json())
            model.model_validate(checked.data)
        except (ValidationError, PydanticSerializationError, ValueError, RecursionError) as exc:
            self._invalid.inc()
            if self._log_limit.allow("invalid"):
                error = (
                    str(exc.errors(include_url=False, include_input=False))
                    if isinstance(exc, ValidationError)
                    else f"{type(exc).__name__}: {exc}"
                )
                self.log.error(
                    "extension_refused",
                    type=event.type[:64],
                    reason="invalid",
                    error=error[:500],
                    refused=int(self._invalid.value),
                )
            return None
        return checked
