"""SWECCIS: Functional Area Service documents and five-line orders over TLS (docs/sweccis.md).

One integration, one package.

The FAS codec (``fas``, its XML helpers ``fasxml``), the five-line order (``order``), the
TLS link with client certificates (``link``), the sink (``sink``) and the order source
(``source``).
"""

from __future__ import annotations

from sinks.sweccis.sink import SweccisSink, SweccisSinkConfig
from sinks.sweccis.source import SweccisSource, SweccisSourceConfig

__all__ = ["SweccisSink", "SweccisSinkConfig", "SweccisSource", "SweccisSourceConfig"]
