"""sd_notify datagrams to a real AF_UNIX socket, and the watchdog period."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import anyio
import pytest

from gateway.sdnotify import SystemdNotifier


def test_ready_stopping_and_watchdog_reach_the_socket(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.settimeout(2)
        notifier = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "30000000"})
        notifier.ready("2 links")
        notifier.watchdog()
        notifier.stopping()
        received = [sock.recv(1024) for _ in range(3)]
    assert received == [b"READY=1\nSTATUS=2 links", b"WATCHDOG=1", b"STOPPING=1"]
    assert notifier.watchdog_interval_s == 15.0


def test_without_systemd_everything_is_a_no_op() -> None:
    notifier = SystemdNotifier({})
    notifier.ready()
    assert not notifier.is_enabled
    assert notifier.watchdog_interval_s is None


def test_watchdog_for_another_pid_is_ignored(tmp_path: Path) -> None:
    env = {"NOTIFY_SOCKET": str(tmp_path / "n"), "WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"}
    assert os.getpid() != 1
    assert SystemdNotifier(env).watchdog_interval_s is None


@pytest.mark.anyio
async def test_run_watchdog_pings_from_the_loop(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.setblocking(False)
        notifier = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "20000"})
        with anyio.fail_after(5):
            async with anyio.create_task_group() as tg:
                await tg.start(notifier.run_watchdog)
                pings = 0
                while pings < 3:
                    await anyio.wait_readable(sock)
                    assert sock.recv(64) == b"WATCHDOG=1"
                    pings += 1
                tg.cancel_scope.cancel()
