"""A plugin's own ``status()`` read for /status without letting it take /status down.

A sink's, source's or processor's ``status()`` is plugin code: one that raises would otherwise
end the whole /status answer (the health listener closes the connection). ``read_status`` calls
it and, if it raises or returns something that is not a mapping, gives ``{"status_error": ...}``
in its place and logs at most once a minute per plugin.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import structlog

from gateway.ops.logsetup import RateLimit

__all__ = ["read_status"]

log = structlog.get_logger(__name__)
_limit = RateLimit(interval_s=60.0)


def read_status(call: Callable[[], Any], plugin: str) -> dict[str, Any] | None:
    """``call()`` as a dict (None stays None); its failure as ``{"status_error": ...}``."""
    try:
        found = call()
    except Exception as exc:  # noqa: BLE001 - plugin code: any failure is reported, not raised
        problem = f"{type(exc).__name__}: {exc}"[:200]
    else:
        if found is None or isinstance(found, Mapping):
            return None if found is None else dict(found)
        problem = f"status() returned {type(found).__name__}, not a mapping"
    if _limit.allow(plugin[:64]):
        log.error("plugin_status_failed", plugin=plugin[:64], error=problem)
    return {"status_error": problem}
