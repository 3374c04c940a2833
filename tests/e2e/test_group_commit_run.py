"""Five CoT UDP sinks behind the spool, the way an operator runs it: ``fischer-gateway run``.

An airframe on an unsecured UDP link sends detections one at a time; each must reach all
five receivers once, in the order sent, be acknowledged HELD once it is committed, and leave
nothing owed in the spool. The spool's commits are counted (``fg_spool_commits_total``): the
writes of a loop pass share one, and the five sinks' confirmations of one detection share
one, so a detection costs about two commits, where one per write would be six. Loopback only.
"""

from __future__ import annotations

import re
import socket
from pathlib import Path

import pytest

from tests.daemon_support import Airframe, free_udp_port, running, wait_until

pytestmark = pytest.mark.timeout(90)

DETECTIONS = 30
SINKS = 5
UID = re.compile(rb'uid="(fischer-det-[^"]+)"')  # the detection's own event


def write_node(tmp_path: Path, link: int, receivers: list[int]) -> Path:
    sinks = "\n".join(
        f"  - {{name: cot{i}, type: cot, options: {{destinations: "
        f"[{{uri: 'udp://127.0.0.1:{port}'}}]}}}}"
        for i, port in enumerate(receivers)
    )
    names = ", ".join(f"cot{i}" for i in range(len(receivers)))
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
spool: {{path: '{tmp_path / "spool.db"}'}}
airframes:
  - id: F26E-001
    sysid: 1
    links: [{{uri: 'udp://127.0.0.1:{link}', security: unsecured, name: fleet}}]
sinks:
{sinks}
routes:
  - {{sinks: [{names}], kinds: [detection]}}
"""
    )
    return config


def receive(sock: socket.socket, uids: list[bytes]) -> None:
    """Everything waiting on ``sock``: the uid of each CoT event in it."""
    while True:
        try:
            data = sock.recv(65_535)
        except BlockingIOError:
            return
        uids.extend(UID.findall(data))


def test_every_detection_reaches_five_sinks_once_in_order_with_grouped_commits(
    tmp_path: Path,
) -> None:
    receivers = []
    for _ in range(SINKS):
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        receivers.append(sock)
    got: list[list[bytes]] = [[] for _ in receivers]
    link = free_udp_port()
    config = write_node(tmp_path, link, [s.getsockname()[1] for s in receivers])
    airframe = Airframe(1)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        with running(config) as daemon:
            daemon.wait_event("gateway_started", 30)
            out.sendto(airframe.heartbeat() + airframe.position(), ("127.0.0.1", link))
            before = daemon.metric("fg_spool_commits_total")
            for n in range(1, DETECTIONS + 1):
                out.sendto(airframe.detection(), ("127.0.0.1", link))

                def arrived(n: int = n) -> bool:
                    for sock, uids in zip(receivers, got, strict=True):
                        receive(sock, uids)
                    return all(len(uids) >= n for uids in got)

                wait_until(arrived, 20, f"detection {n} at all {SINKS} receivers")
            wait_until(lambda: daemon.metric("fg_spool_pending_events") == 0, 10, "nothing owed")
            commits = daemon.metric("fg_spool_commits_total") - before
            held = daemon.metric(
                "fg_detections_acknowledged_total", airframe="F26E-001", result="held"
            )
    finally:
        out.close()
        for sock in receivers:
            sock.close()
    assert held == DETECTIONS
    first = got[0]
    assert len(first) == len(set(first)) == DETECTIONS  # each once
    order = [int(uid.rsplit(b"-", 2)[1]) for uid in first]
    assert order == list(range(1, DETECTIONS + 1))  # in the order sent
    assert all(uids == first for uids in got)  # the same at every sink
    # At most about two per detection (its datagram's, then the five confirmations', which
    # the next datagram's often joins): 33 for 30 here on an idle machine; six per detection
    # if each write committed on its own. Generous: a loaded machine may split a group.
    assert commits <= 4 * DETECTIONS
