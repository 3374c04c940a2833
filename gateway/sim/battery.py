"""A simulated GUTE II battery for the demo: an HTTPS endpoint that takes handoff cues.

A ``PostServer`` (loopback TLS, client certificate from the demo CA required) whose new
cues go to ``on_handoff`` once per ``Idempotency-Key``. It plays the battery's side only as
far as the demo needs: the operator's decision to engage is not simulated, because the
gateway never makes it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from gateway.sim.httpspost import PostServer
from gateway.sim.pki import DemoPki

__all__ = ["SimulatedBattery"]


class SimulatedBattery(PostServer):
    """See the module docstring; its loopback port is bound (``port``) when it is made."""

    def __init__(self, pki: DemoPki, on_handoff: Callable[[dict[str, Any]], None]) -> None:
        super().__init__(pki, lambda _path, document: on_handoff(document))
