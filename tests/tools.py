"""Debian tools some tests need (espeak-ng, ffmpeg, chromium): skip without them, unless CI
promised them.

``.ci/run`` installs each tool on its own and lists it in ``FG_REQUIRED_TOOLS``; a tool listed
there but missing (its install failed) is then a failure, never a quiet skip, so CI really runs
the tests that need it.
"""

from __future__ import annotations

import os
import shutil

import pytest


def required(name: str) -> bool:
    """True when CI installed ``name`` and its tests must run."""
    return name in os.environ.get("FG_REQUIRED_TOOLS", "").split()


def skip_without(*names: str) -> pytest.MarkDecorator:
    """A skipif marker for when any of ``names`` is missing and not required."""
    missing = [n for n in names if shutil.which(n) is None]
    promised = [n for n in missing if required(n)]
    return pytest.mark.skipif(
        bool(missing) and not promised,
        reason=f"{', '.join(missing) or 'nothing'} not installed (.ci/run installs it)",
    )


def need(name: str) -> None:
    """Skip the running test without ``name``; fail if CI promised it (``FG_REQUIRED_TOOLS``)."""
    if shutil.which(name) is not None:
        return
    if required(name):
        pytest.fail(f"{name} is required here (FG_REQUIRED_TOOLS) but not on PATH")
    pytest.skip(f"{name} is not installed (.ci/run installs it)")
