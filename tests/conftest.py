"""Shared fixtures: every async test runs on asyncio and on asyncio with uvloop."""

from __future__ import annotations

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
