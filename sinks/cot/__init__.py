"""Cursor-on-Target: ATAK/WinTAK and TAK servers (docs/cot.md).

One integration, one package.

The CoT XML and TAK protocol codecs (``event``, ``codec``, ``proto``), the
validator of what peers send (``validate``), the sink's UDP mesh and TCP/TLS transports
(``udp``, ``transport``), the sink (``sink``) and the source that reads CoT from ATAK's SA mesh
and TAK streams (``source``, ``stream``).
"""

from __future__ import annotations

from sinks.cot.sink import CotSink, CotSinkConfig
from sinks.cot.source import CotSource, CotSourceConfig

__all__ = ["CotSink", "CotSinkConfig", "CotSource", "CotSourceConfig"]
