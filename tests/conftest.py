"""Shared fixtures: every async test runs on asyncio and on asyncio with uvloop.

Tests under the directories in ``SLOW_DIRS`` (the daemon run end to end, attacked, faulted)
are marked ``slow``: ``pytest -m "not slow"`` is the quick loop while working, and plain
``pytest`` (what CI runs) still runs everything.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import structlog
import uvloop


@pytest.fixture(autouse=True, scope="session")
def quiet_logs() -> None:
    """Log records go nowhere unless a test captures them (``structlog.testing``)."""
    structlog.configure(
        processors=[structlog.processors.JSONRenderer()],
        logger_factory=structlog.ReturnLoggerFactory(),
        cache_logger_on_first_use=False,
    )


@pytest.fixture(
    params=[
        pytest.param(("asyncio", {}), id="asyncio"),
        pytest.param(("asyncio", {"loop_factory": uvloop.new_event_loop}), id="uvloop"),
    ]
)
def anyio_backend(request: pytest.FixtureRequest) -> tuple[str, dict[str, object]]:
    """The anyio backend and its options for this test."""
    return request.param  # type: ignore[no-any-return]


HERE = Path(__file__).resolve().parent
#: Directories whose every test is ``slow``.
SLOW_DIRS = tuple(HERE / name for name in ("e2e", "attack", "faults"))


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark every test under ``SLOW_DIRS`` ``slow``."""
    for item in items:
        if any(item.path.is_relative_to(directory) for directory in SLOW_DIRS):
            item.add_marker(pytest.mark.slow)
