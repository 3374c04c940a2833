"""The live map: a page served by the node, and its change stream (docs/map.md).

One integration, one package.

The picture the map keeps (``picture``), the stream's fan-out (``hub``), the options and the
rule for binding beyond loopback (``config``), the web application (``web``, Starlette), its
server (``server``, hypercorn in the daemon's event loop) and the sink (``sink``). The page
and the vendored libraries it runs on are in ``static/``.
"""

from __future__ import annotations

from sinks.map.config import MapSinkConfig
from sinks.map.sink import MapSink

__all__ = ["MapSink", "MapSinkConfig"]
