"""Edges of the command policy a cold red-team pass found, through ``fischer-gateway run``.

One airframe on an unsecured link (a socket here that reads everything the gateway sends
it), its passthrough ``uplink: open`` with ``param_set_allow: ['*']``, the broadest an
operator may write. A local process without a key sends:

- DO_SET_MODE whose base mode (param1, a float) is 1e10 or NaN. Python's ``int(1e10) & 128``
  is 0, but an autopilot casts param1 to a byte in C, and an ARM core saturates 1e10 to
  0xFF: the armed flag. Such a mode change was relayed from an open uplink; NaN ended in an
  ``internal_error`` and went unanswered. Both are arming now (signed uplink only), answered
  DENIED.
- PARAM_SET ``servo9_function`` and PARAM_EXT_SET ``relay1_function``: ArduPilot finds some
  parameters whatever their case, and the never-list was matched case-sensitively.

- MISSION_START: PX4's commander arms to start a mission ("switch to AUTO_MISSION and ARM"),
  so it was an arming command any local process could send. Signed uplink only now.

A parameter the allow-list does take (MPC_XY_CRUISE) goes last: once the airframe has it,
everything before it was handled.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

import pytest
from daemon_support import Airframe, free_udp_port, running, wait_until
from pymavlink.dialects.v20 import ardupilotmega as mav

pytestmark = pytest.mark.timeout(60)

SYSID = 7


def test_out_of_range_modes_and_parameter_case_are_refused(tmp_path: Path) -> None:
    link_port, gcs_port = free_udp_port(), free_udp_port()
    config = tmp_path / "node.yaml"
    config.write_text(
        "gateway: {shutdown_deadline_s: 2}\nhealth: {port: 0}\nairframes:\n"
        f"  - id: EDGE\n    sysid: {SYSID}\n    link_timeout_s: 3600\n"
        f"    passthrough: {{uri: 'udp://127.0.0.1:{gcs_port}', uplink: open,"
        " param_set_allow: ['*']}\n"
        f"    links: [{{uri: 'udp://127.0.0.1:{link_port}', security: unsecured}}]\n"
    )
    airframe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    airframe.bind(("127.0.0.1", 0))
    airframe.settimeout(0.05)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(("127.0.0.1", 0))
    stranger.settimeout(0.5)
    received: list[Any] = []
    reader = mav.MAVLink(None)

    def drain() -> list[Any]:
        while True:
            try:
                data = airframe.recv(4096)
            except TimeoutError:
                return received
            received.extend(reader.parse_buffer(data) or ())

    try:
        with running(config) as daemon:
            airframe.sendto(Airframe(SYSID).heartbeat(), ("127.0.0.1", link_port))
            wait_until(
                lambda: daemon.status()["airframes"][0]["active_link"], 20, "the airframe linked"
            )
            gcs = mav.MAVLink(None, srcSystem=255, srcComponent=190)
            nan = float("nan")
            refused = [
                gcs.command_long_encode(SYSID, 1, 176, 0, 1e10, 4, 0, 0, 0, 0, 0),
                gcs.command_int_encode(SYSID, 1, 0, 176, 0, 0, 1e10, 4, 0, 0, 0, 0, 0),
                gcs.command_long_encode(SYSID, 1, 176, 0, nan, 4, 0, 0, 0, 0, 0),
                gcs.command_long_encode(SYSID, 1, 300, 0, 0, 0, 0, 0, 0, 0, 0),  # PX4 arms
                gcs.param_set_encode(SYSID, 1, b"servo9_function", 1, 9),
                gcs.param_ext_set_encode(SYSID, 1, b"relay1_function", b"1", 6),
            ]
            for msg in refused:
                stranger.sendto(bytes(msg.pack(gcs)), ("127.0.0.1", gcs_port))
            marker = gcs.param_set_encode(SYSID, 1, b"MPC_XY_CRUISE", 12, 9)
            stranger.sendto(bytes(marker.pack(gcs)), ("127.0.0.1", gcs_port))
            wait_until(
                lambda: any(m.get_type() == "PARAM_SET" for m in drain()),
                15,
                "the allowed parameter relayed",
            )
            time.sleep(0.2)
            got = [m for m in drain() if m.get_type() != "HEARTBEAT"]
            assert [(m.get_type(), m.param_id) for m in got] == [("PARAM_SET", "MPC_XY_CRUISE")]
            status = daemon.status()["passthroughs"][0]
            assert status["refused"] == {"parameter": 2, "signed_only": 4}
            denied = []
            answers = mav.MAVLink(None)
            while len(denied) < 4:
                for msg in answers.parse_buffer(stranger.recv(4096)) or ():
                    if msg.get_type() == "COMMAND_ACK":
                        assert msg.result == mav.MAV_RESULT_DENIED
                        denied.append(msg.command)
            assert denied == [176, 176, 176, 300]
            assert not daemon.events("passthrough_internal_error")
            assert daemon.get("/healthz")[0] == 200
    finally:
        airframe.close()
        stranger.close()
