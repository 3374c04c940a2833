"""Local processes against the passthrough, through ``fischer-gateway run``.

One daemon holds nine airframes: each link security (tunnel, signed, unsecured) with each
uplink mode (none, signed, open), every passthrough listening on loopback, plus one signed
uplink in connect mode whose ground-station port a squatter holds. Each airframe's link is a
socket here that authenticates for it and decodes everything the gateway sends it (opening
the tunnel, checking signatures with pymavlink). Then a local process with no key sends every
passthrough effector commands, gateway-only messages and each class of bad input; a ground
station with the right key sends the same effectors and a legitimate request.

What must hold (issue #21): no effector command reaches any airframe from any local process;
no gateway-only message is relayed; arming only from a signed ground station; a wrong or
missing key is refused; the daemon is alive after every bad input and counts what it refused.
"""

from __future__ import annotations

import hashlib
import os
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest
from daemon_support import (
    MASTER,
    SIGNING_KEY,
    Airframe,
    Daemon,
    free_udp_port,
    sealer,
    wait_until,
    write_key,
)
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.errors import FrameError
from gateway.fleet.dialect import MAVLINK_MSG_ID_FISCHER_DETECTION_ACK, fischer_detection_ack
from gateway.fleet.hopdialect import MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE, FischerHopSchedule
from gateway.fleet.security.signing import mavlink_timestamp_now
from gateway.fleet.uplinkpolicy import EFFECTOR_COMMANDS, SIGNED_ONLY_COMMANDS, may_arm

pytestmark = pytest.mark.timeout(180)

GCS_KEY = hashlib.sha256(b"attack-test-ground-station").digest()
WRONG_KEY = hashlib.sha256(b"a key nobody configured").digest()
SECURITIES = ("tunnel", "signed", "unsecured")
UPLINKS = ("none", "signed", "open")
GATEWAY_ONLY = {MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE, MAVLINK_MSG_ID_FISCHER_DETECTION_ACK}
EFFECTOR_ITEMS = EFFECTOR_COMMANDS


@dataclass
class Node:
    """The airframe side of one configured airframe, and its passthrough's port."""

    id: str
    sysid: int
    security: str
    uplink: str
    link_port: int
    gcs_port: int
    sock: socket.socket = field(init=False)
    received: list[Any] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.frames = Airframe(
            self.sysid, signing_key=SIGNING_KEY if self.security == "signed" else None
        )
        self._sealer = sealer(self.id) if self.security == "tunnel" else None
        self._opener = self._sealer.reply_opener() if self._sealer is not None else None
        self._parser = mav.MAVLink(None)
        if self.security == "signed":
            self._parser.signing.secret_key = SIGNING_KEY

    def hello(self) -> None:
        """An authenticated heartbeat: the gateway learns this socket as the uplink peer."""
        frame = self.frames.heartbeat()
        data = self._sealer.seal(frame) if self._sealer is not None else frame
        self.sock.sendto(data, ("127.0.0.1", self.link_port))

    def drain(self) -> list[Any]:
        """Decode everything the gateway sent this airframe since the last call."""
        while True:
            try:
                data = self.sock.recv(4096)
            except (TimeoutError, BlockingIOError):
                return self.received
            if self._opener is not None:
                try:
                    data = self._opener.open_frame(data).payload
                except FrameError as exc:  # pragma: no cover - would be a gateway bug
                    raise AssertionError(f"{self.id}: uplink that does not open: {exc}") from exc
            for msg in self._parser.parse_buffer(data) or ():
                assert msg.get_type() != "BAD_DATA", f"{self.id}: bad frame {msg}"
                if self.security == "signed":
                    assert msg.get_signed(), f"{self.id}: unsigned uplink on a signed link"
                self.received.append(msg)


def ground_station(key: bytes | None, sysid: int = 255) -> Any:
    gcs = mav.MAVLink(None, srcSystem=sysid, srcComponent=190)
    if key is not None:
        gcs.signing.secret_key = key
        gcs.signing.link_id = 1
        gcs.signing.sign_outgoing = True
        gcs.signing.timestamp = mavlink_timestamp_now(time.time())
    return gcs


def effector_frames(gcs: Any, target: int) -> list[bytes]:
    """Every way the red team moved an output, and the review's additions."""
    frames = [
        gcs.command_long_encode(target, 1, command, 0, 9, 1900, 3, 1, 0, 0, 0)
        for command in sorted(EFFECTOR_COMMANDS | SIGNED_ONLY_COMMANDS)
    ]
    frames += [
        gcs.command_long_encode(target, 1, 400, 0, 1, 21196, 0, 0, 0, 0, 0),  # forced arm
        gcs.mission_clear_all_encode(target, 1, 1),  # the geofence cleared
        gcs.command_long_encode(target, 1, 179, 0, 0, 0, 0, 0, 59.0, 18.0, 0),  # home moved
        gcs.request_data_stream_encode(target, 1, 0, 0, 0),  # telemetry stopped
        gcs.command_long_encode(target, 1, 176, 0, 128 | 1, 4, 0, 0, 0, 0, 0),  # armed flag
        # No armed bit in Python, 0xFF after an ARM core's saturating cast to a byte.
        gcs.command_long_encode(target, 1, 176, 0, 1e10, 4, 0, 0, 0, 0, 0),
        gcs.command_int_encode(target, 1, 0, 176, 0, 0, float("nan"), 4, 0, 0, 0, 0, 0),
        gcs.set_mode_encode(target, 128 | 1, 4),
        gcs.command_int_encode(target, 1, 0, 183, 0, 0, 9, 1900, 0, 0, 0, 0, 0),
        gcs.mission_item_int_encode(target, 1, 0, 0, 183, 0, 1, 9, 1900, 0, 0, 0, 0, 0, 0),
        gcs.mission_item_encode(target, 1, 1, 0, 211, 0, 1, 1, 0, 0, 0, 0, 0, 0, 0),
        gcs.param_set_encode(target, 1, b"SERVO9_FUNCTION", 1, 9),
        gcs.param_set_encode(target, 1, b"MPC_XY_CRUISE", 20, 9),  # not allowed either
        gcs.param_ext_set_encode(target, 1, b"RELAY1_FUNCTION", b"1", 6),
        gcs.set_actuator_control_target_encode(0, 0, target, 1, [1.0] * 8),
        gcs.rc_channels_override_encode(target, 1, *([1900] * 18)),
        gcs.manual_control_encode(target, 0, 0, 500, 0, 0xFFFF),
        gcs.setup_signing_encode(target, 1, [0] * 32, 0),
        gcs.serial_control_encode(10, 0, 0, 0, 4, [ord(c) for c in "rebo"] + [0] * 66),
        gcs.file_transfer_protocol_encode(0, target, 1, [0, 0, 0, 7] + [0] * 247),  # write
        gcs.log_erase_encode(target, 1),
        gcs.command_long_encode(target + 20, 1, 512, 0, 33, 0, 0, 0, 0, 0, 0),  # wrong target
        FischerHopSchedule(0, [2_405_000_000] + [0] * 7, 77, 10_000_000, 100_000, 0, target, 1, 1),
        fischer_detection_ack(1, 1, target, 1, 0),
    ]
    return [bytes(frame.pack(gcs)) for frame in frames]


def bad_inputs(target: int) -> list[bytes]:
    """Each class of bad input the issue names: none may end the daemon."""
    v1 = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    heartbeat_v1 = bytes(v1.heartbeat_encode(6, 8, 0, 0, 4).pack(v1, force_mavlink1=True))
    servo_v1 = bytes(
        v1.command_long_encode(target, 1, 183, 0, 9, 1900, 0, 0, 0, 0, 0).pack(
            v1, force_mavlink1=True
        )
    )
    gcs = ground_station(None)
    good = bytes(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs))
    unknown = bytearray(good)
    unknown[7:10] = (0xABCDE).to_bytes(3, "little")  # an id no dialect knows
    return [
        b"\x00" * 5,
        os.urandom(64),
        b"\xfd\xff" + os.urandom(20),
        heartbeat_v1,
        servo_v1,
        bytes(unknown),
        good[:7],
        good[:-1],
        b"\xfd" * 2000,
        os.urandom(3000),
        good * 40,
    ]


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Daemon, list[Node], Any]]:
    tmp = tmp_path_factory.mktemp("passthrough")
    master = write_key(tmp / "master.key", MASTER)
    signing = write_key(tmp / "signing.key", SIGNING_KEY)
    gcs_key = write_key(tmp / "gcs.key", GCS_KEY)
    nodes = []
    blocks = []
    for i, (security, uplink) in enumerate((s, u) for s in SECURITIES for u in UPLINKS):
        n = Node(
            f"{security[:3].upper()}-{uplink.upper()}",
            i + 1,
            security,
            uplink,
            free_udp_port(),
            free_udp_port(),
        )
        nodes.append(n)
        key = f", key_file: '{gcs_key}'" if uplink == "signed" else ""
        sign = f"    signing: {{key_file: '{signing}'}}\n" if security == "signed" else ""
        blocks.append(
            f"  - id: {n.id}\n    sysid: {n.sysid}\n    link_timeout_s: 3600\n{sign}"
            f"    passthrough: {{uri: 'udp://127.0.0.1:{n.gcs_port}', uplink: {uplink}{key}}}\n"
            f"    links: [{{uri: 'udp://127.0.0.1:{n.link_port}', security: {security}}}]\n"
        )
    # A signed uplink in connect mode: a squatter holds the ground station's port.
    squatter = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    squatter.bind(("127.0.0.1", 0))
    squatter.settimeout(0.05)
    connect = Node("CON-SIGNED", 10, "unsecured", "signed", free_udp_port(), 0)
    nodes.append(connect)
    blocks.append(
        f"  - id: {connect.id}\n    sysid: 10\n    link_timeout_s: 3600\n"
        "    passthrough: {uri: "
        f"'udp://127.0.0.1:{squatter.getsockname()[1]}?mode=connect', uplink: signed, "
        f"key_file: '{gcs_key}'}}\n"
        f"    links: [{{uri: 'udp://127.0.0.1:{connect.link_port}', security: unsecured}}]\n"
    )
    config = tmp / "node.yaml"
    config.write_text(
        "gateway: {shutdown_deadline_s: 2}\nhealth: {port: 0}\n"
        f"tunnel: {{master_key_file: '{master}'}}\nairframes:\n" + "".join(blocks)
    )
    daemon = Daemon(config)
    try:
        for n in nodes:
            # A signing clock that starts after the gateway's (see test_restart_replay.py).
            n.frames = Airframe(n.sysid, signing_key=n.frames.mav.signing.secret_key)
            n.hello()
        wait_until(
            lambda: all(a["active_link"] for a in daemon.status()["airframes"]),
            20,
            "every airframe linked",
        )
        yield daemon, nodes, squatter
    finally:
        assert daemon.proc.poll() is None, "the daemon ended during the attack"
        daemon.stop()
        squatter.close()
        for n in nodes:
            n.sock.close()


def passthrough(daemon: Daemon, airframe: str) -> dict[str, Any]:
    return next(p for p in daemon.status()["passthroughs"] if p["airframe"] == airframe)


def uplinked(n: Node) -> list[Any]:
    """What the gateway sent the airframe beyond its own traffic (it sends none here)."""
    return n.drain()


def assert_no_effector(n: Node, *, arming_ok: bool) -> None:
    for msg in uplinked(n):
        msgid = msg.get_msgId()
        assert msgid not in GATEWAY_ONLY, f"{n.id}: gateway-only {msg.get_type()} relayed"
        assert msg.get_type() not in {
            "PARAM_SET",
            "PARAM_EXT_SET",
            "SET_ACTUATOR_CONTROL_TARGET",
            "RC_CHANNELS_OVERRIDE",
            "MANUAL_CONTROL",
            "SETUP_SIGNING",
            "SERIAL_CONTROL",
            "LOG_ERASE",
            "FILE_TRANSFER_PROTOCOL",
        }, f"{n.id}: {msg.get_type()} relayed"
        command = getattr(msg, "command", None)
        if msg.get_type() in ("COMMAND_LONG", "COMMAND_INT"):
            assert command not in EFFECTOR_COMMANDS, f"{n.id}: effector {command} relayed"
            if command in SIGNED_ONLY_COMMANDS or (command == 176 and may_arm(msg.param1)):
                assert arming_ok, f"{n.id}: {command} relayed from an unsigned ground station"
            assert msg.target_system == n.sysid
        if msg.get_type() in ("MISSION_ITEM", "MISSION_ITEM_INT"):
            assert command not in EFFECTOR_ITEMS, f"{n.id}: effector mission item relayed"
        if msg.get_type() == "SET_MODE":
            assert arming_ok or not msg.base_mode & 128
        # The airframe's own safety settings: only from a signed station.
        if msg.get_type() == "MISSION_CLEAR_ALL":
            assert arming_ok or msg.mission_type == 0, f"{n.id}: geofence cleared"
        if msg.get_type() == "REQUEST_DATA_STREAM":
            assert arming_ok or msg.start_stop, f"{n.id}: telemetry stopped"
        if command == 179:
            assert arming_ok, f"{n.id}: home moved from an unsigned station"


def test_no_local_process_moves_an_effector_or_ends_the_daemon(
    node: tuple[Daemon, list[Node], Any],
) -> None:
    daemon, nodes, _squatter = node
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.settimeout(0.05)
    try:
        for n in nodes[:9]:
            for key in (None, WRONG_KEY):
                for frame in effector_frames(ground_station(key), n.sysid):
                    stranger.sendto(frame, ("127.0.0.1", n.gcs_port))
            for datagram in bad_inputs(n.sysid):
                stranger.sendto(datagram, ("127.0.0.1", n.gcs_port))
            # And one thing a ground station may ask: only an open uplink relays it from here.
            gcs = ground_station(None)
            request = gcs.command_long_encode(n.sysid, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0)
            stranger.sendto(bytes(request.pack(gcs)), ("127.0.0.1", n.gcs_port))
        # A flood of mixed junk at one passthrough: bounded, counted, the node keeps serving.
        flood = bad_inputs(1) + effector_frames(ground_station(None), 1)
        for i in range(5000):
            stranger.sendto(flood[i % len(flood)], ("127.0.0.1", nodes[2].gcs_port))
        # A genuine heartbeat after everything: once the airframe hears its relayed copy, all
        # that went before it on that passthrough was handled.
        gcs = ground_station(None)
        marker = bytes(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs))
        stranger.sendto(marker, ("127.0.0.1", nodes[2].gcs_port))
        wait_until(
            lambda: any(m.get_type() == "HEARTBEAT" for m in uplinked(nodes[2])),
            30,
            "the heartbeat behind the flood relayed",
        )
        for n in nodes[:9]:
            wait_until(
                lambda n=n: passthrough(daemon, n.id)["uplink_refused"] >= 40,
                15,
                f"{n.id}'s refusals counted",
            )
    finally:
        stranger.close()
    time.sleep(0.3)  # anything relayed late would be on the airframes' sockets by now
    assert daemon.get("/healthz")[0] == 200
    for n in nodes[:9]:
        assert_no_effector(n, arming_ok=False)
        status = passthrough(daemon, n.id)
        refused = status["refused"]
        requests = [m for m in n.received if m.get_type() == "COMMAND_LONG" and m.command == 512]
        assert len(requests) == (1 if n.uplink == "open" else 0), n.id
        if n.uplink == "none":
            assert status["uplink_frames"] == 0
            assert all(m.get_type() != "COMMAND_LONG" for m in n.received)
        elif n.uplink == "signed":
            # Unsigned and wrongly signed: nothing of the stranger's reached the airframe.
            assert status["uplink_frames"] == 0, n.id
            assert refused["signature_auth"] > 0
        else:
            assert refused["effector"] > 0
            assert refused["gateway_only"] >= 2 * 2
            assert refused["signed_only"] > 0
            assert refused["parameter"] > 0
        assert refused["mavlink1"] >= 2
        assert refused["malformed"] > 0
        assert refused["unknown_msgid"] >= 1
        assert refused["oversize"] >= 1
    assert daemon.metric("fg_passthrough_refused_total", reason="effector") > 0
    # Logged, not per frame: at most one line per passthrough and reason in this short run.
    lines = daemon.events("passthrough_uplink_refused")
    assert len(lines) <= len({(e["airframe"], e["reason"]) for e in lines}) * 2
    assert all("sender" in e and e["sender"].startswith("127.0.0.1:") for e in lines)


def test_a_signed_ground_station_flies_but_moves_no_effector(
    node: tuple[Daemon, list[Node], Any],
) -> None:
    """The right key: a request and arming go through, effectors are refused and answered."""
    daemon, nodes, _squatter = node
    station = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    station.bind(("127.0.0.1", 0))
    station.settimeout(0.3)
    answers = mav.MAVLink(None)
    answers.signing.secret_key = GCS_KEY
    try:
        for n in (x for x in nodes[:9] if x.uplink == "signed"):
            gcs = ground_station(GCS_KEY)
            before = passthrough(daemon, n.id)["uplink_frames"]
            frames = [
                bytes(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs)),
                bytes(gcs.command_long_encode(n.sysid, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs)),
                *effector_frames(gcs, n.sysid),
            ]
            for frame in frames:
                station.sendto(frame, ("127.0.0.1", n.gcs_port))
            wait_until(
                lambda n=n, before=before: passthrough(daemon, n.id)["uplink_frames"] >= before + 3,
                15,
                f"{n.id}: heartbeat, arm and the signed-only commands relayed",
            )
            time.sleep(0.3)
            got = uplinked(n)
            assert_no_effector(n, arming_ok=True)
            assert any(m.get_type() == "COMMAND_LONG" and m.command == 400 for m in got)
            denied = []
            while True:
                try:
                    data = station.recv(4096)
                except TimeoutError:
                    break
                for msg in answers.parse_buffer(data) or ():
                    assert msg.get_signed(), "the answer to a signed station is signed"
                    if msg.get_type() == "COMMAND_ACK":
                        denied.append(msg.command)
            assert set(EFFECTOR_COMMANDS) <= set(denied), n.id
            assert answers.signing.badsig_count == 0
    finally:
        station.close()


def test_a_squatter_on_a_connect_mode_port_is_refused_and_harmless(
    node: tuple[Daemon, list[Node], Any],
) -> None:
    """A local user binds the configured ground station's port while it is free: it reads
    the airframe's telemetry (signed with a key it lacks) but its frames, MAVLink 1 or
    unsigned, go nowhere and do not end the node."""
    daemon, nodes, squatter = node
    connect = nodes[9]
    connect.frames = Airframe(connect.sysid)
    connect.sock.sendto(connect.frames.position(), ("127.0.0.1", connect.link_port))
    got = b""
    deadline = time.monotonic() + 10
    while not got and time.monotonic() < deadline:
        try:
            got = squatter.recv(4096)
        except TimeoutError:
            connect.sock.sendto(connect.frames.position(), ("127.0.0.1", connect.link_port))
    # It reads the telemetry (signing is not secrecy), signed with a key it does not hold.
    assert got[0] == 0xFD
    assert got[2] & 0x01
    for datagram in [*bad_inputs(10), *effector_frames(ground_station(None), 10)]:
        squatter.sendto(datagram, ("127.0.0.1", _gateway_side_port(daemon, connect.id)))
    # The airframe's own frame, signed with the station's key on its way out, sent back in:
    # the signature is good, but a ground station never speaks as the airframe.
    squatter.sendto(got, ("127.0.0.1", _gateway_side_port(daemon, connect.id)))
    wait_until(
        lambda: passthrough(daemon, connect.id)["refused"].get("airframe_source", 0) >= 1,
        15,
        "the reflected frame refused",
    )
    wait_until(
        lambda: passthrough(daemon, connect.id)["uplink_refused"] >= 20, 15, "refusals counted"
    )
    assert passthrough(daemon, connect.id)["uplink_frames"] == 0
    assert_no_effector(connect, arming_ok=False)
    assert daemon.get("/healthz")[0] == 200


def _gateway_side_port(daemon: Daemon, airframe: str) -> int:
    for line in daemon.events("link_bound"):
        if line.get("link") == f"{airframe}-gcs":
            return int(line["local"].rsplit(",", 1)[1].strip(" )'\""))
    raise AssertionError(f"no link_bound line for {airframe}'s passthrough")
