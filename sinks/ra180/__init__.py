"""Ra 180: Compact Data Messages and a Swedish voice announcement (docs/ra180.md).

One integration, one package.

The 127-character CDM codec (``cdm``), the Swedish phrases (``phrases``), the net's airtime
budget (``budget``), the voice (``voice``) and the sink (``sink``).
"""

from __future__ import annotations

from sinks.ra180.sink import Ra180Sink, Ra180SinkConfig

__all__ = ["Ra180Sink", "Ra180SinkConfig"]
