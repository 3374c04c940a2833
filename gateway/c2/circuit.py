"""A circuit breaker for one sink, with jittered exponential backoff from tenacity.

Closed: batches are sent as they come. After ``threshold`` failed calls in a row the circuit
opens: nothing is sent until the backoff delay has passed. Then it is half-open: one probe (a
batch of one event) is sent; success closes the circuit, failure opens it again for a longer
delay. The delay before attempt *n* is tenacity's full-jitter exponential backoff
(``wait_random_exponential``: uniform in [0, min(max, initial · 2^(n-1))]), so many gateways
recovering together do not retry in lock step. The state is exported as
``fg_sink_circuit_state`` for alerting.
"""

from __future__ import annotations

from enum import IntEnum

from tenacity import RetryCallState, wait_random_exponential

__all__ = ["Circuit", "CircuitState"]


class CircuitState(IntEnum):
    """The breaker's state, as the gauge exports it."""

    CLOSED = 0
    HALF_OPEN = 1
    OPEN = 2


class Circuit:
    """Counts failures in a row and says how long to wait and how much to send."""

    def __init__(self, *, initial_s: float, max_s: float, threshold: int = 3) -> None:
        self.threshold = threshold
        self.max_s = max_s
        self._wait = wait_random_exponential(multiplier=initial_s, max=max_s)
        self._call = RetryCallState(retry_object=None, fn=None, args=(), kwargs={})  # type: ignore[arg-type]
        self.failures_in_row = 0
        self.state = CircuitState.CLOSED

    def failed(self) -> float:
        """Record a failed call; the delay before the next attempt, in seconds."""
        self.failures_in_row += 1
        if self.failures_in_row >= self.threshold:
            self.state = CircuitState.OPEN
        # Past 64 doublings the delay is max_s anyway; keeps 2**n a small number.
        self._call.attempt_number = min(self.failures_in_row, 64)
        return float(self._wait(self._call))

    def probing(self) -> bool:
        """Called before an attempt: True if it is a half-open probe (send one event)."""
        if self.state is CircuitState.OPEN:
            self.state = CircuitState.HALF_OPEN
        return self.state is CircuitState.HALF_OPEN

    def succeeded(self) -> int:
        """Record a successful call; how many failures in a row it ended."""
        ended, self.failures_in_row = self.failures_in_row, 0
        self.state = CircuitState.CLOSED
        return ended
