"""The node's map page in headless Chromium (Debian's, driven by Playwright), for tests.

``map_page`` opens the page a node serves with every request beyond the node refused and
remembered, collects the page's script errors, and waits for its first snapshot. Where CI
promised the browser (``tests/tools.py``: ``required``) a missing Playwright fails the test
instead of skipping it.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import pytest
from tools import need, required

__all__ = ["CHROMIUM_FLAGS", "MapPage", "map_page"]

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


@dataclass
class MapPage:
    """The open page, and what it asked for and raised so far."""

    page: Any
    requested: list[str] = field(default_factory=list)
    foreign: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


@contextmanager
def map_page(url: str) -> Iterator[MapPage]:
    """The map at ``url``, loaded and showing its first snapshot; the browser closed after."""
    need("chromium")
    if required("chromium"):  # CI promised the browser test: no skip for a missing driver
        import playwright.sync_api as sync_api
    else:
        sync_api = pytest.importorskip("playwright.sync_api", reason="playwright (test extra)")
    origin = url.rstrip("/")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=shutil.which("chromium"), headless=True, args=CHROMIUM_FLAGS
        )
        try:
            shown = MapPage(browser.new_page(viewport={"width": 1280, "height": 800}))

            def only_the_node(route: Any) -> None:
                shown.requested.append(route.request.url)
                if route.request.url.startswith(origin + "/"):
                    route.continue_()
                else:
                    shown.foreign.append(route.request.url)
                    route.abort()

            shown.page.route("**/*", only_the_node)
            shown.page.on("pageerror", lambda exc: shown.errors.append(str(exc)))
            shown.page.goto(url)
            shown.page.wait_for_function("() => window.fgMap && window.fgMap.state.snapshots >= 1")
            yield shown
        finally:
            browser.close()
