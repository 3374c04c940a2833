"""SLB (Saab battalion C2): JC3IEDM object items out, orders in, over HTTPS (docs/slb.md).

One integration, one package.

The JC3IEDM object-item codec (``jc3iedm``), the order document (``order``, also read by
the local order source), the sink (``sink``) and the order source (``source``).
"""

from __future__ import annotations

from sinks.slb.sink import SlbSink, SlbSinkConfig
from sinks.slb.source import SlbSource, SlbSourceConfig

__all__ = ["SlbSink", "SlbSinkConfig", "SlbSource", "SlbSourceConfig"]
