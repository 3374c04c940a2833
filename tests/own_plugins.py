"""The plugin types fischer-gateway itself registers, for the tests that loop over plugins.

A test that enumerated every installed type would also pick up a third-party plugin installed
in the same environment and run it with options it cannot know; these list only our own.
"""

from __future__ import annotations

import re
from importlib.metadata import entry_points

__all__ = ["PROJECT", "own_types"]

#: The project's distribution name, normalised (PEP 503).
PROJECT = "fischer-gateway"


def own_types(group: str) -> list[str]:
    """The entry-point names of ``group`` that the fischer-gateway distribution provides."""
    return sorted(
        ep.name
        for ep in entry_points(group=group)
        if ep.dist is not None and re.sub(r"[-_.]+", "-", ep.dist.name).lower() == PROJECT
    )
