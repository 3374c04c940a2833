"""The ``process_*`` metrics Prometheus' own clients export, read from ``/proc/self``.

Same names, units and meaning as prometheus_client's process collector, so the usual
dashboards and alert rules work. Read at scrape time. The start time is not taken from
``/proc/stat``'s boot time, as that collector does: the unit's ``ProcSubset=pid`` hides
``/proc/stat``, so the boot time comes from ``CLOCK_BOOTTIME`` instead. Outside Linux (no
``/proc/self``) the families are registered but empty.
"""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Iterable
from pathlib import Path

from gateway.ops.metrics import Registry

__all__ = ["ProcessStats", "register_process_metrics"]

_PROC = Path("/proc/self")


class ProcessStats:
    """Reads this process' resource use from ``/proc/self``; every method may return None."""

    def __init__(self, proc: Path = _PROC) -> None:
        self._proc = proc
        self._ticks = os.sysconf("SC_CLK_TCK")
        self._page = os.sysconf("SC_PAGESIZE")
        self._start_time_s: float | None = None

    def _stat_fields(self) -> list[str] | None:
        try:
            text = (self._proc / "stat").read_text()
        except OSError:
            return None
        # Field 2 (comm) is in parentheses and may hold spaces; fields after it start at 3.
        return text[text.rindex(")") + 2 :].split()

    def cpu_seconds(self) -> float | None:
        """User plus system CPU time, in seconds."""
        fields = self._stat_fields()
        if fields is None:
            return None
        return (int(fields[11]) + int(fields[12])) / self._ticks  # utime, stime (14, 15)

    def start_time_s(self) -> float | None:
        """When the process started, in seconds since the UNIX epoch (computed once)."""
        if self._start_time_s is None:
            fields = self._stat_fields()
            if fields is None:
                return None
            since_boot_s = int(fields[19]) / self._ticks  # starttime (22), ticks since boot
            boot_s = time.time() - time.clock_gettime(time.CLOCK_BOOTTIME)
            self._start_time_s = boot_s + since_boot_s
        return self._start_time_s

    def memory_bytes(self) -> tuple[float, float] | None:
        """(virtual, resident) memory in bytes."""
        try:
            size, resident, *_ = (self._proc / "statm").read_text().split()
        except (OSError, ValueError):
            return None
        return int(size) * self._page, int(resident) * self._page

    def open_fds(self) -> int | None:
        """File descriptors open now."""
        try:
            return len(os.listdir(self._proc / "fd"))
        except OSError:
            return None

    @staticmethod
    def max_fds() -> int:
        """The soft limit on open file descriptors (``RLIMIT_NOFILE``)."""
        return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


def _one(value: float | None) -> Iterable[tuple[tuple[str, ...], float]]:
    return [] if value is None else [((), float(value))]


def register_process_metrics(registry: Registry, stats: ProcessStats | None = None) -> None:
    """Add the ``process_*`` families to ``registry``, computed at each scrape."""
    s = stats or ProcessStats()

    def memory(index: int) -> Iterable[tuple[tuple[str, ...], float]]:
        found = s.memory_bytes()
        return _one(None if found is None else found[index])

    registry.counter(
        "process_cpu_seconds_total", "Total user and system CPU time spent in seconds."
    ).set_function(lambda: _one(s.cpu_seconds()))
    registry.gauge("process_virtual_memory_bytes", "Virtual memory size in bytes.").set_function(
        lambda: memory(0)
    )
    registry.gauge("process_resident_memory_bytes", "Resident memory size in bytes.").set_function(
        lambda: memory(1)
    )
    registry.gauge(
        "process_start_time_seconds", "Start time of the process since unix epoch in seconds."
    ).set_function(lambda: _one(s.start_time_s()))
    registry.gauge("process_open_fds", "Number of open file descriptors.").set_function(
        lambda: _one(s.open_fds())
    )
    registry.gauge("process_max_fds", "Maximum number of open file descriptors.").set_function(
        lambda: _one(s.max_fds())
    )
