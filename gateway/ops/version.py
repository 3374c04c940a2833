"""The installed distribution's version, for ``--version``, ``/status`` and ``fg_build_info``."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

__all__ = ["package_version"]


def package_version() -> str:
    """The version of the installed ``fischer-gateway`` distribution, or ``unknown``."""
    try:
        return version("fischer-gateway")
    except PackageNotFoundError:
        return "unknown"
