"""GUTE II counter-UAS battery: track handoffs as JSON over HTTPS (docs/counter-uas.md).

One integration, one package.

The handoff document and its schema versions (``codec``) and the sink that POSTs it
(``sink``). A handoff is a cue with a recommendation for the battery's operator; nothing here
can command an effector.
"""

from __future__ import annotations

from sinks.gute2.sink import GuteSink, GuteSinkConfig

__all__ = ["GuteSink", "GuteSinkConfig"]
