"""fischer-gateway: binds the Fischer 26E fleet's MAVLink links to C2 systems.

The public surface for embedding the gateway and for third-party sinks is re-exported here;
everything else is internal and may change. The names load on first use, so importing one
submodule (``gateway.errors``, say) does not pull in the whole daemon and cannot close an
import cycle through this package.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from gateway.app import Gateway as Gateway
    from gateway.c2.sink import LifetimeSink as LifetimeSink
    from gateway.c2.sink import Sink as Sink
    from gateway.c2.sink import SinkConfig as SinkConfig
    from gateway.c2.source import Source as Source
    from gateway.c2.source import SourceConfig as SourceConfig
    from gateway.clock import Clock as Clock
    from gateway.config import Config as Config
    from gateway.configfile import load_config as load_config
    from gateway.errors import GatewayError as GatewayError
    from gateway.errors import PermanentSinkError as PermanentSinkError
    from gateway.errors import TransientSinkError as TransientSinkError
    from gateway.events import Event as Event
    from gateway.events import EventKind as EventKind
    from gateway.flow.processor import Processor as Processor
    from gateway.flow.processor import ProcessorConfig as ProcessorConfig
    from gateway.flow.processor import Publish as Publish

__all__ = [
    "Clock",
    "Config",
    "Event",
    "EventKind",
    "Gateway",
    "GatewayError",
    "LifetimeSink",
    "PermanentSinkError",
    "Processor",
    "ProcessorConfig",
    "Publish",
    "Sink",
    "SinkConfig",
    "Source",
    "SourceConfig",
    "TransientSinkError",
    "load_config",
]

_HOME = {
    "Clock": "gateway.clock",
    "Config": "gateway.config",
    "Event": "gateway.events",
    "EventKind": "gateway.events",
    "Gateway": "gateway.app",
    "GatewayError": "gateway.errors",
    "LifetimeSink": "gateway.c2.sink",
    "Processor": "gateway.flow.processor",
    "ProcessorConfig": "gateway.flow.processor",
    "Publish": "gateway.flow.processor",
    "Source": "gateway.c2.source",
    "SourceConfig": "gateway.c2.source",
    "PermanentSinkError": "gateway.errors",
    "Sink": "gateway.c2.sink",
    "SinkConfig": "gateway.c2.sink",
    "TransientSinkError": "gateway.errors",
    "load_config": "gateway.configfile",
}


def __getattr__(name: str) -> Any:
    home = _HOME.get(name)
    if home is None:
        raise AttributeError(f"module 'gateway' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
