"""sd_notify datagrams to a real AF_UNIX socket, and the watchdog period."""

from __future__ import annotations

import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import anyio
import pytest
from structlog.testing import capture_logs

from gateway.ops.sdnotify import SystemdNotifier


@pytest.fixture
def notify_socket(tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    """A bound AF_UNIX datagram socket standing in for systemd, and its path."""
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.setblocking(False)
        yield path, sock


def drain(sock: socket.socket) -> list[bytes]:
    """Every datagram already queued on ``sock`` (sends to AF_UNIX are synchronous)."""
    received = []
    while True:
        try:
            received.append(sock.recv(4096))
        except BlockingIOError:
            return received


def test_each_notification_is_one_datagram(notify_socket: tuple[str, socket.socket]) -> None:
    path, sock = notify_socket
    notifier = SystemdNotifier({"NOTIFY_SOCKET": path})
    notifier.ready("2 links")
    notifier.ready()
    notifier.status("draining sinks")
    notifier.watchdog()
    notifier.stopping()
    assert drain(sock) == [
        b"READY=1\nSTATUS=2 links",
        b"READY=1",
        b"STATUS=draining sinks",
        b"WATCHDOG=1",
        b"STOPPING=1",
    ]
    assert notifier.is_enabled
    assert notifier.failures == 0


def test_status_text_cannot_inject_other_assignments(
    notify_socket: tuple[str, socket.socket],
) -> None:
    path, sock = notify_socket
    notifier = SystemdNotifier({"NOTIFY_SOCKET": path})
    notifier.status("up\nREADY=1")
    notifier.ready("a\r\nWATCHDOG=1")
    notifier.status("lone \ud800 surrogate")
    assert drain(sock) == [
        b"STATUS=up READY=1",
        b"READY=1\nSTATUS=a WATCHDOG=1",
        b"STATUS=lone ? surrogate",
    ]
    assert notifier.failures == 0


def test_abstract_socket_is_addressed_with_a_leading_nul() -> None:
    name = f"fischer-gateway-test-{uuid.uuid4().hex}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        sock.setblocking(False)
        SystemdNotifier({"NOTIFY_SOCKET": "@" + name}).ready()
        assert drain(sock) == [b"READY=1"]


def test_environment_is_read_by_default(
    notify_socket: tuple[str, socket.socket], monkeypatch: pytest.MonkeyPatch
) -> None:
    path, sock = notify_socket
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "4000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    notifier = SystemdNotifier()
    notifier.watchdog()
    assert drain(sock) == [b"WATCHDOG=1"]
    assert notifier.watchdog_interval_s == 2.0


def test_without_notify_socket_everything_is_a_no_op() -> None:
    notifier = SystemdNotifier({"WATCHDOG_USEC": "30000000"})
    notifier.ready("x")
    notifier.status("x")
    notifier.watchdog()
    notifier.stopping()
    assert not notifier.is_enabled
    assert notifier.watchdog_interval_s is None
    assert notifier.failures == 0


def test_send_failure_is_counted_and_logged_not_raised(tmp_path: Path) -> None:
    notifier = SystemdNotifier({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    with capture_logs() as logs:
        notifier.ready("x")
        notifier.watchdog()
    assert notifier.failures == 2
    assert [(e["event"], e["notification"], e["log_level"]) for e in logs] == [
        ("sd_notify_failed", "READY", "warning"),
        ("sd_notify_failed", "WATCHDOG", "warning"),
    ]


@pytest.mark.parametrize("address", ["vsock:2:1234", "relative/path", "@"])
def test_unusable_socket_address_disables_notifications(address: str) -> None:
    with capture_logs() as logs:
        notifier = SystemdNotifier({"NOTIFY_SOCKET": address, "WATCHDOG_USEC": "1000000"})
        notifier.ready()
    assert not notifier.is_enabled
    assert notifier.watchdog_interval_s is None
    assert [e["event"] for e in logs] == ["sd_notify_socket_unsupported"]


@pytest.mark.parametrize(
    ("env", "interval_s"),
    [
        pytest.param({"WATCHDOG_USEC": "30000000"}, 15.0, id="half-of-usec"),
        pytest.param({"WATCHDOG_USEC": "20000", "WATCHDOG_PID": "<self>"}, 0.01, id="our-pid"),
        pytest.param({"WATCHDOG_USEC": "20000", "WATCHDOG_PID": "<other>"}, None, id="other-pid"),
        pytest.param({"WATCHDOG_USEC": "20000", "WATCHDOG_PID": "x"}, None, id="bad-pid"),
        pytest.param({"WATCHDOG_USEC": "0"}, None, id="zero"),
        pytest.param({"WATCHDOG_USEC": "-5"}, None, id="negative"),
        pytest.param({"WATCHDOG_USEC": "²"}, None, id="unicode-digit"),
        pytest.param({"WATCHDOG_USEC": "5s"}, None, id="not-a-number"),
        pytest.param({}, None, id="unset"),
    ],
)
def test_watchdog_interval_is_half_of_watchdog_usec_for_this_process(
    tmp_path: Path, env: dict[str, str], interval_s: float | None
) -> None:
    pids = {"<self>": str(os.getpid()), "<other>": str(os.getpid() + 1)}
    env = {k: pids.get(v, v) for k, v in env.items()}
    notifier = SystemdNotifier({"NOTIFY_SOCKET": str(tmp_path / "n"), **env})
    assert notifier.watchdog_interval_s == interval_s


@pytest.mark.anyio
async def test_run_watchdog_pings_from_the_loop(notify_socket: tuple[str, socket.socket]) -> None:
    path, sock = notify_socket
    notifier = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "20000"})
    pings: list[bytes] = []
    with anyio.fail_after(5):
        async with anyio.create_task_group() as tg:
            await tg.start(notifier.run_watchdog)
            while len(pings) < 3:
                await anyio.wait_readable(sock)
                pings += drain(sock)
            tg.cancel_scope.cancel()
    assert set(pings) == {b"WATCHDOG=1"}
    assert notifier.failures == 0


@pytest.mark.anyio
async def test_run_watchdog_returns_at_once_without_a_watchdog(
    notify_socket: tuple[str, socket.socket],
) -> None:
    path, sock = notify_socket
    with anyio.fail_after(5):
        await SystemdNotifier({"NOTIFY_SOCKET": path}).run_watchdog()
        await SystemdNotifier({}).run_watchdog()
    assert drain(sock) == []
