"""SIGHUP: check the config file again and say whether it differs from the running one.

A full reload (new routes and sinks without dropping the links) is not done yet: the
components are built once, from one ``Config``, in ``Gateway.__init__``, and swapping sinks
under a running bus needs the sink runners' lifetime rework first. So SIGHUP only
re-validates the file and logs ``config_reload_checked`` (valid; which top-level sections
changed; ``applied=False``, restart to apply) or ``config_reload_rejected`` (every problem).
The running gateway is never touched. See docs/operations.md.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import anyio.to_thread
import structlog

from gateway.c2.plugins import check_sink
from gateway.config import Config
from gateway.configfile import load_config
from gateway.errors import ConfigError

__all__ = ["changed_sections", "recheck_config"]

log = structlog.get_logger(__name__)


def changed_sections(running: Config, new: Config) -> list[str]:
    """The top-level config sections whose values differ, in the config's order."""
    before, after = running.model_dump(mode="json"), new.model_dump(mode="json")
    return [key for key in after if before.get(key) != after[key]]


async def recheck_config(path: Path, running: Config) -> list[str] | None:
    """Load ``path`` again (in a worker thread) and log how it compares with ``running``.

    Returns the changed sections, or None if the file is not a valid config. Never raises
    for a bad file: a reload request must not take the daemon down.
    """
    try:
        new = await anyio.to_thread.run_sync(partial(load_config, path, check_sink=check_sink))
    except ConfigError as exc:
        log.error(
            "config_reload_rejected",
            path=str(path),
            issues=[str(issue) for issue in exc.issues],
            applied=False,
        )
        return None
    except OSError as exc:
        log.error("config_reload_rejected", path=str(path), issues=[str(exc)], applied=False)
        return None
    changed = changed_sections(running, new)
    # A warning when it differs: the operator asked for a change that is not in effect.
    level = log.warning if changed else log.info
    level(
        "config_reload_checked",
        path=str(path),
        changed=changed,
        applied=False,
        action="restart to apply" if changed else "none",
    )
    return changed
