"""systemd's notify protocol without a dependency: READY, STOPPING, STATUS and WATCHDOG.

``STATUS=`` is refreshed while the daemon runs (``run_status``), so ``systemctl status``
shows the fleet as it is now, not as it was at start-up.

A no-op when the daemon does not run under systemd (``NOTIFY_SOCKET`` unset). The watchdog
is fed from a task on the event loop, so a stuck loop stops the pings and systemd restarts
the daemon. Sending never raises: a lost notification must not take the gateway down, so
failures are counted in ``failures`` and logged.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable, Mapping

import anyio
import anyio.abc
import structlog

__all__ = ["SystemdNotifier"]

log = structlog.get_logger(__name__)

#: How often ``run_status`` refreshes ``STATUS=`` by default.
STATUS_INTERVAL_S = 10.0


def _positive_int(text: str) -> int | None:
    # str.isdigit accepts "²" and other digits int() refuses; systemd writes plain ASCII.
    return int(text) if text.isascii() and text.isdigit() and int(text) > 0 else None


class SystemdNotifier:
    """Sends sd_notify datagrams to ``$NOTIFY_SOCKET`` (a path, or ``@name`` for abstract)."""

    def __init__(
        self, env: Mapping[str, str] | None = None, *, status_interval_s: float = STATUS_INTERVAL_S
    ) -> None:
        env = os.environ if env is None else env
        self.status_interval_s = status_interval_s
        """How often ``run_status`` refreshes ``STATUS=``."""
        address = env.get("NOTIFY_SOCKET", "")
        self._address: str | None = None
        if address.startswith("/"):
            self._address = address
        elif address.startswith("@") and len(address) > 1:
            # A leading '@' names a socket in Linux's abstract namespace, a leading NUL byte.
            self._address = "\0" + address[1:]
        elif address:
            # Newer systemd may hand out vsock: addresses; we speak AF_UNIX only.
            log.warning("sd_notify_socket_unsupported", address=address)
        self.failures = 0
        """Notifications that could not be sent."""
        usec = _positive_int(env.get("WATCHDOG_USEC", ""))
        pid_text = env.get("WATCHDOG_PID", "")
        # Without WATCHDOG_PID the watchdog is ours; with it, only if it names this process
        # (a child that inherited the environment must not feed its parent's watchdog).
        is_ours = not pid_text or _positive_int(pid_text) == os.getpid()
        self._watchdog_interval_s = usec / 2e6 if usec is not None and is_ours else None

    @property
    def is_enabled(self) -> bool:
        """True when running under systemd with a usable notify socket."""
        return self._address is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """Half of systemd's WatchdogSec in seconds, or None when there is no watchdog."""
        return self._watchdog_interval_s if self.is_enabled else None

    def _send(self, message: str) -> None:
        if self._address is None:
            return
        try:
            # A fresh unbound socket per message: notifications are rare, and nothing is held
            # open across fork or between the (seconds apart) watchdog pings.
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
                sock.setblocking(False)
                sock.sendto(message.encode("utf-8", "replace"), self._address)
        except OSError as exc:
            self.failures += 1
            notification = message.split("=", 1)[0]
            log.warning("sd_notify_failed", notification=notification, error=str(exc))

    def ready(self, status: str = "") -> None:
        """Tell systemd start-up is complete, optionally with a status line."""
        self._send("READY=1" + (f"\nSTATUS={_one_line(status)}" if status else ""))

    def stopping(self) -> None:
        """Tell systemd the daemon is shutting down."""
        self._send("STOPPING=1")

    def status(self, text: str) -> None:
        """Set the status line ``systemctl status`` shows."""
        self._send(f"STATUS={_one_line(text)}")

    def watchdog(self) -> None:
        """Feed the watchdog once."""
        self._send("WATCHDOG=1")

    async def run_watchdog(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Feed the watchdog every ``watchdog_interval_s`` until cancelled.

        Returns at once (after reporting started) when there is no watchdog. The first ping
        goes out immediately. Cancellation-safe: it holds nothing between pings.
        """
        task_status.started()
        interval = self.watchdog_interval_s
        if interval is None:
            return
        # A fixed schedule rather than sleep(interval) after each ping, so the period does not
        # drift; after a stall the schedule restarts from now instead of bursting to catch up.
        next_ping_s = anyio.current_time()
        while True:
            self.watchdog()
            next_ping_s += interval
            now_s = anyio.current_time()
            if next_ping_s <= now_s:
                next_ping_s = now_s + interval
            await anyio.sleep_until(next_ping_s)

    async def run_status(
        self,
        summary: Callable[[], str],
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Send ``STATUS=summary()`` now and every ``status_interval_s`` when it changed.

        Returns at once (after reporting started) when not under systemd. Cancellation-safe.
        """
        task_status.started()
        if not self.is_enabled:
            return
        last = None
        while True:
            text = _one_line(summary())
            if text != last:
                self.status(text)
                last = text
            await anyio.sleep(self.status_interval_s)


def _one_line(text: str) -> str:
    # The protocol is newline-separated assignments: a newline in a status text would let it
    # smuggle in READY=1 or WATCHDOG=1.
    return " ".join(text.splitlines())
