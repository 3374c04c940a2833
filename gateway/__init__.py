"""fischer-gateway: binds the Fischer 26E fleet's MAVLink links to C2 systems.

The public surface for embedding the gateway and for third-party sinks is re-exported here;
everything else is internal and may change.
"""

from gateway.app import Gateway as Gateway
from gateway.config import Config as Config
from gateway.configfile import load_config as load_config
from gateway.errors import GatewayError as GatewayError
from gateway.errors import PermanentSinkError as PermanentSinkError
from gateway.errors import TransientSinkError as TransientSinkError
from gateway.events import Event as Event
from gateway.events import EventKind as EventKind
from gateway.sink import Sink as Sink
from gateway.sink import SinkConfig as SinkConfig

__all__ = [
    "Config",
    "Event",
    "EventKind",
    "Gateway",
    "GatewayError",
    "PermanentSinkError",
    "Sink",
    "SinkConfig",
    "TransientSinkError",
    "load_config",
]
