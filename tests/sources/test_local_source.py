"""The local order source: its Unix socket, the peer check, and what it answers."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import anyio
import pytest

from gateway.events import Event, FiveLineOrder, OrderState, OrderStatus
from sources.local import LocalOrderSource, LocalOrderSourceConfig

ORDER = {
    "order_id": "OP-9",
    "issued": "2026-11-22T12:00:00Z",
    "task": "observe_point",
    "location": {"point": {"lat_deg": 65.85, "lon_deg": 21.1}},
}


async def exchange(path: Path, payload: bytes) -> list[dict[str, object]]:
    async with await anyio.connect_unix(path) as stream:
        await stream.send(payload)
        data = b""
        with anyio.fail_after(5):
            try:
                while True:
                    data += await stream.receive()
            except anyio.EndOfStream:
                pass
    return [json.loads(line) for line in data.splitlines()]


@pytest.mark.anyio
async def test_an_order_is_published_and_its_statuses_streamed_until_final(
    tmp_path: Path,
) -> None:
    published: list[Event] = []
    arrived = anyio.Event()

    def publish(event: Event) -> bool:
        published.append(event)
        arrived.set()
        return True

    config = LocalOrderSourceConfig(socket=tmp_path / "o.sock")
    source = LocalOrderSource("operator", config, publish)

    async def answer() -> None:
        await arrived.wait()
        order = published[0]
        assert isinstance(order, FiveLineOrder)
        for state in (OrderState.ACCEPTED, OrderState.FAILED):
            source.on_order_status(
                OrderStatus(
                    event_id=f"{order.event_id}-{state.value}",
                    order_event_id=order.event_id,
                    order_id=order.order_id,
                    source="operator",
                    time=order.time,
                    status=state,
                    check="command" if state is OrderState.FAILED else None,
                    reason="no COMMAND_ACK" if state is OrderState.FAILED else None,
                )
            )

    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            assert stat.S_IMODE(config.socket.stat().st_mode) == 0o600
            tg.start_soon(answer)
            lines = await exchange(config.socket, json.dumps(ORDER).encode() + b"\n")
            tg.cancel_scope.cancel()
    assert [line["status"] for line in lines] == ["received", "accepted", "failed"]
    assert lines[-1]["reason"] == "no COMMAND_ACK"
    (order,) = published
    assert isinstance(order, FiveLineOrder)
    assert order.event_id == "local-order-OP-9"
    assert order.source == "operator"
    assert not config.socket.exists()  # removed on the way out


@pytest.mark.anyio
async def test_a_taken_order_id_is_rejected_again_or_a_conflict_if_changed(tmp_path: Path) -> None:
    published: list[Event] = []

    def publish(event: Event) -> bool:
        published.append(event)
        assert isinstance(event, FiveLineOrder)
        source.on_order_status(  # answered at once: the first order's final status
            OrderStatus(
                event_id=f"{event.event_id}-completed",
                order_event_id=event.event_id,
                order_id=event.order_id,
                source="operator",
                time=event.time,
                status=OrderState.COMPLETED,
            )
        )
        return True

    config = LocalOrderSourceConfig(socket=tmp_path / "o.sock")
    source = LocalOrderSource("operator", config, publish)
    later = {**ORDER, "issued": "2026-11-22T12:05:00Z"}  # issued again, the same order
    changed = {**ORDER, "location": {"point": {"lat_deg": 65.9, "lon_deg": 21.2}}}
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            answers = [
                await exchange(config.socket, json.dumps(o).encode() + b"\n")
                for o in (ORDER, later, changed)
            ]
            tg.cancel_scope.cancel()
    assert [[a["status"] for a in lines] for lines in answers] == [
        ["received", "completed"],
        ["rejected"],
        ["conflict"],
    ]
    assert answers[2][0]["reason"] == (
        "order_id: OP-9 was already taken with other content; the first stands: give a"
        " changed order a new id"
    )
    assert len(published) == 1
    assert source.counts["conflict"] == 1


@pytest.mark.anyio
async def test_bad_lines_are_answered_rejected_and_nothing_is_published(tmp_path: Path) -> None:
    published: list[Event] = []
    config = LocalOrderSourceConfig(socket=tmp_path / "o.sock", max_line_bytes=1024, timeout_s=0.5)
    source = LocalOrderSource("operator", config, lambda e: published.append(e) or True)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            bad_task = json.dumps({**ORDER, "task": "fire_mission"}).encode() + b"\n"
            answers = [
                await exchange(config.socket, b"[1, 2\n"),
                await exchange(config.socket, b"x" * 5000),
                await exchange(config.socket, b"no newline"),
                await exchange(config.socket, bad_task),
            ]
            tg.cancel_scope.cancel()
    assert [a[0]["status"] for a in answers] == ["rejected"] * 4
    assert answers[0][0]["reason"] == "order: not JSON"
    assert answers[1][0]["reason"] == "order: no end of line within max_line_bytes (1024)"
    assert str(answers[3][0]["reason"]).startswith("task: ")
    assert published == []
    assert source.counts["malformed"] == 1


@pytest.fixture
def open_directory() -> Iterator[Path]:
    """A directory every user may reach (pytest's own tmp tree is the owner's only)."""
    path = Path(tempfile.mkdtemp(prefix="fg-local-"))
    path.chmod(0o755)
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to connect as another user")
@pytest.mark.anyio
async def test_a_peer_of_another_uid_is_refused_even_through_an_open_socket(
    open_directory: Path,
) -> None:
    published: list[Event] = []
    config = LocalOrderSourceConfig(socket=open_directory / "o.sock", socket_mode=0o666)
    source = LocalOrderSource("operator", config, lambda e: published.append(e) or True)
    client = (
        "import os, socket, sys\n"
        "os.setgid(65534); os.setuid(65534)\n"
        "s = socket.socket(socket.AF_UNIX); s.settimeout(5); s.connect(sys.argv[1])\n"
        "try:\n"
        "    s.sendall(sys.argv[2].encode() + b'\\n'); print(repr(s.recv(100)))\n"
        "except (BrokenPipeError, ConnectionResetError):\n"
        "    print(repr(b''))  # closed before the order was even written\n"
    )
    with anyio.fail_after(20):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            done = await anyio.run_process(
                [sys.executable, "-c", client, str(config.socket), json.dumps(ORDER)],
                check=False,
            )
            tg.cancel_scope.cancel()
    assert done.stdout.decode().strip() == "b''", done.stderr.decode()  # closed unanswered
    assert published == []
    assert source.counts["refused_peer"] == 1


def test_the_command_says_when_the_daemon_is_not_there(tmp_path: Path) -> None:
    command = [sys.executable, "-m", "gateway", "order", "--socket", str(tmp_path / "none")]
    command += ["--task", "return_to_base", "--point", "65.8", "21.0"]
    done = subprocess.run(command, capture_output=True, timeout=30, check=False)
    assert done.returncode == 2
    assert str(tmp_path / "none") in done.stderr.decode()


class Archive:
    """Statuses kept for orders (the spool's order book, as ``keep_statuses`` sees it)."""

    def __init__(self, kept: dict[str, list[OrderStatus]]) -> None:
        self.kept = kept

    def statuses(self, order_event_id: str) -> list[OrderStatus]:
        return self.kept.get(order_event_id, [])


def kept_status(state: OrderState, seq: int) -> OrderStatus:
    return OrderStatus(
        event_id=f"local-order-OP-9-{state.value}",
        order_event_id="local-order-OP-9",
        order_id="OP-9",
        source="operator",
        time="2026-11-22T12:00:00Z",
        status=state,
        seq=seq,
    )


@pytest.mark.anyio
async def test_the_statuses_kept_for_an_order_are_answered_by_seq(tmp_path: Path) -> None:
    published: list[Event] = []
    config = LocalOrderSourceConfig(socket=tmp_path / "o.sock")
    source = LocalOrderSource("operator", config, lambda e: published.append(e) or True)
    states = (OrderState.ACCEPTED, OrderState.EXECUTING, OrderState.COMPLETED)
    archive = Archive({"local-order-OP-9": [kept_status(s, n) for n, s in enumerate(states, 1)]})
    source.keep_statuses(archive)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            kept = await exchange(config.socket, b'{"status_of": "OP-9"}\n')
            unknown = await exchange(config.socket, b'{"status_of": "OP-10"}\n')
            bad = await exchange(config.socket, b'{"status_of": 7}\n')
            # Taken before a restart (its statuses are kept): the same id is refused.
            again = await exchange(config.socket, json.dumps(ORDER).encode() + b"\n")
            tg.cancel_scope.cancel()
    assert [(line["seq"], line["status"]) for line in kept] == [
        (1, "accepted"),
        (2, "executing"),
        (3, "completed"),
    ]
    assert [line["status"] for line in unknown] == ["unknown"]
    assert [line["status"] for line in bad] == ["rejected"]
    assert [line["status"] for line in again] == ["rejected"]
    assert "order --status OP-9" in str(again[0]["reason"])
    assert published == []


def test_the_command_asks_for_the_statuses_of_an_order(tmp_path: Path) -> None:
    command = [sys.executable, "-m", "gateway", "order", "--socket", str(tmp_path / "none")]
    done = subprocess.run([*command, "--status", "OP-9"], capture_output=True, timeout=30)
    assert done.returncode == 2  # the daemon is not there
    done = subprocess.run(command, capture_output=True, timeout=30, check=False)
    assert done.returncode == 2
    assert "--task and one of --point, --mgrs, --polygon are required" in done.stderr.decode()


@pytest.mark.anyio
async def test_a_client_gone_before_its_next_status_ends_only_its_connection(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A client that reads ``received`` and hangs up just as the next status comes: writing
    that status fails (EPIPE) before the hang-up is noticed. Only that connection ends,
    counted ``client_gone``; the source goes on serving (it failed, and its socket went
    away while it restarted, before)."""
    import sources.local as local

    async def never_noticed(_stream: object, _scope: object) -> None:
        await anyio.sleep_forever()  # the hang-up lost the race to the status

    monkeypatch.setattr(local, "_until_hangup", never_noticed)
    published: list[FiveLineOrder] = []

    def publish(event: Event) -> bool:
        assert isinstance(event, FiveLineOrder)
        published.append(event)
        return True

    config = LocalOrderSourceConfig(socket=tmp_path / "o.sock")
    source = LocalOrderSource("operator", config, publish)

    def accepted(order: FiveLineOrder) -> OrderStatus:
        return OrderStatus(
            event_id=f"{order.event_id}-accepted",
            order_event_id=order.event_id,
            order_id=order.order_id,
            source="operator",
            time=order.time,
            status=OrderState.ACCEPTED,
        )

    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            async with await anyio.connect_unix(config.socket) as stream:
                await stream.send(json.dumps(ORDER).encode() + b"\n")
                assert json.loads(await stream.receive())["status"] == "received"
            source.on_order_status(accepted(published[0]))
            await anyio.wait_all_tasks_blocked()
            assert source.counts["client_gone"] == 1
            second = {**ORDER, "order_id": "OP-10"}
            async with await anyio.connect_unix(config.socket) as stream:
                await stream.send(json.dumps(second).encode() + b"\n")
                assert json.loads(await stream.receive())["status"] == "received"
            tg.cancel_scope.cancel()
    assert [order.order_id for order in published] == ["OP-9", "OP-10"]
