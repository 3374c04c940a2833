"""The one status table of the HTTPS sinks, and how a server's Retry-After is read."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from gateway.transports.https import classify_answer, retry_after_s

NOW = datetime(2026, 11, 22, 12, 0, 0, tzinfo=UTC)
URL = "https://slb.example/api/object-items"


def clock() -> datetime:
    return NOW


class TestClassify:
    """2xx delivered, 409 duplicate, retry when the server asks or is down, else refused."""

    @pytest.mark.parametrize(
        ("status", "outcome"),
        [
            (200, "delivered"),
            (201, "delivered"),
            (202, "delivered"),
            (204, "delivered"),
            (409, "duplicate"),
            (301, "retry"),
            (308, "retry"),
            (401, "retry"),
            (403, "retry"),
            (408, "retry"),
            (425, "retry"),
            (429, "retry"),
            (500, "retry"),
            (503, "retry"),
            (599, "retry"),
            (400, "refused"),
            (404, "refused"),
            (413, "refused"),
            (415, "refused"),
            (422, "refused"),
        ],
    )
    def test_table(self, status: int, outcome: str) -> None:
        answer = classify_answer(URL, status, {}, "why", max_retry_after_s=60, clock=clock)
        assert answer.outcome == outcome
        if outcome in ("retry", "refused"):
            assert f"HTTP {status}" in answer.detail

    def test_a_redirect_names_where_and_asks_to_fix_the_url(self) -> None:
        answer = classify_answer(
            URL, 302, {"location": "https://elsewhere/"}, "", max_retry_after_s=60
        )
        assert answer.detail == (
            f"{URL}: HTTP 302 redirect to 'https://elsewhere/' not followed; fix the url"
        )

    @pytest.mark.parametrize("status", [429, 503])
    def test_retry_after_is_read_for_429_and_503(self, status: int) -> None:
        answer = classify_answer(
            URL, status, {"retry-after": "12"}, "", max_retry_after_s=60, clock=clock
        )
        assert answer.retry_after_s == 12.0

    @pytest.mark.parametrize("status", [500, 502, 401, 301])
    def test_and_not_for_others(self, status: int) -> None:
        answer = classify_answer(URL, status, {"retry-after": "12"}, "", max_retry_after_s=60)
        assert answer.retry_after_s is None


class TestRetryAfter:
    """Delta-seconds or an HTTP date, bounded, and never an error."""

    def test_seconds_and_dates(self) -> None:
        assert retry_after_s("120", limit_s=300, clock=clock) == 120.0
        date = "Sun, 22 Nov 2026 12:00:30 GMT"
        assert retry_after_s(date, limit_s=300, clock=clock) == 30.0

    def test_bounded_both_ways(self) -> None:
        assert retry_after_s("86400", limit_s=60, clock=clock) == 60.0
        past = "Sun, 22 Nov 2026 11:00:00 GMT"
        assert retry_after_s(past, limit_s=60, clock=clock) == 0.0

    @pytest.mark.parametrize(
        "value", [None, "", "soon", "-5", "1.5", "²", "9" * 100, "Sun, 22 Nov 2026 12:00:30"]
    )
    def test_unreadable_is_none(self, value: str | None) -> None:
        assert retry_after_s(value, limit_s=60, clock=clock) is None

    @given(st.text(max_size=80))
    @example("²")  # str.isdigit says yes, float says no: found by CI
    def test_any_header_is_a_bounded_wait_or_none(self, value: str) -> None:
        wait = retry_after_s(value, limit_s=60, clock=clock)
        assert wait is None or 0.0 <= wait <= 60.0
