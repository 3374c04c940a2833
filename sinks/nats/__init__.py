"""NATS JetStream between gateway nodes: several nodes, one picture (docs/scale-out.md).

One integration, one package: subjects, ids and bodies (``subjects``), the connection with
its credentials from files (``connection``), the streams (``streams``), the sink of this
node's detections and airframe states (``sink``) and the source of other nodes' events
(``source``).
"""

from __future__ import annotations

from sinks.nats.sink import NatsSink, NatsSinkConfig
from sinks.nats.source import NatsSource, NatsSourceConfig

__all__ = ["NatsSink", "NatsSinkConfig", "NatsSource", "NatsSourceConfig"]
