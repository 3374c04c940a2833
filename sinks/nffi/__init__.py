"""NFFI: blue-force reports out and in (the JAS 39 relay; docs/nffi.md).

One integration, one package.

The NFFI 1.3 codec (``codec``), the framing of messages on a stream (``stream``), the sink
(``sink``) and the source of friendly reports (``source``).
"""

from __future__ import annotations

from sinks.nffi.sink import NffiSink, NffiSinkConfig
from sinks.nffi.source import NffiSource, NffiSourceConfig

__all__ = ["NffiSink", "NffiSinkConfig", "NffiSource", "NffiSourceConfig"]
