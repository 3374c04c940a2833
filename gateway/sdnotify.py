"""systemd's notify protocol without a dependency: READY, STOPPING, STATUS and WATCHDOG.

A no-op when the daemon does not run under systemd (``NOTIFY_SOCKET`` unset). The watchdog
is fed from a task on the event loop, so a stuck loop stops the pings and systemd restarts
the daemon.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping

import anyio
import anyio.abc
import structlog

__all__ = ["SystemdNotifier"]

log = structlog.get_logger(__name__)


class SystemdNotifier:
    """Sends sd_notify datagrams to ``$NOTIFY_SOCKET``."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        address = env.get("NOTIFY_SOCKET", "")
        # A leading '@' names a socket in the abstract namespace.
        self._address = "\0" + address[1:] if address.startswith("@") else address
        self.failures = 0
        interval: float | None = None
        usec, pid = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            interval = int(usec) / 1e6 / 2
        self._watchdog_interval_s = interval

    @property
    def is_enabled(self) -> bool:
        """True when running under systemd with a notify socket."""
        return bool(self._address)

    @property
    def watchdog_interval_s(self) -> float | None:
        """Half of systemd's WatchdogSec, or None when no watchdog is configured."""
        return self._watchdog_interval_s if self.is_enabled else None

    def _send(self, message: str) -> None:
        if not self._address:
            return
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
                sock.setblocking(False)
                sock.sendto(message.encode(), self._address)
        except OSError as exc:
            self.failures += 1
            log.warning("sd_notify_failed", error=str(exc))

    def ready(self, status: str = "") -> None:
        """Tell systemd start-up is complete."""
        self._send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def stopping(self) -> None:
        """Tell systemd the daemon is shutting down."""
        self._send("STOPPING=1")

    def status(self, text: str) -> None:
        """Set the status line ``systemctl status`` shows."""
        self._send(f"STATUS={text}")

    def watchdog(self) -> None:
        """Feed the watchdog once."""
        self._send("WATCHDOG=1")

    async def run_watchdog(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Feed the watchdog every half period until cancelled; return at once if none."""
        task_status.started()
        interval = self.watchdog_interval_s
        if interval is None:
            return
        while True:
            self.watchdog()
            await anyio.sleep(interval)
