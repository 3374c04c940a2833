"""An attacker on the node's network, against ``fischer-gateway run`` with all three link modes.

The node has a tunnel airframe (TUN, sysid 1, with a passthrough for a ground station), a
signed airframe (SIG, sysid 2) and an unsecured one (OPEN, sysid 3), each on its own UDP
port on loopback. The attacker has no keys: it sends plain MAVLink carrying the sysids of
TUN and SIG to OPEN's port, garbage to TUN's port, and listens for anything sent back.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from daemon_support import (
    SIGNING_KEY,
    Airframe,
    archive_events,
    free_tcp_port,
    free_udp_port,
    running,
    sealer,
    three_airframe_node,
    wait_until,
)
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.fleet.deframe import frame_for_stream

pytestmark = pytest.mark.timeout(90)


def write_config(tmp_path: Path) -> tuple[Path, dict[str, int], Path]:
    ports = {name: free_udp_port() for name in ("tun", "sig", "open", "gcs")}
    tun_extra = (
        "    link_timeout_s: 0.5\n    failback_hold_s: 0\n"
        f"    passthrough: {{uri: 'udp://127.0.0.1:{ports['gcs']}', uplink: open}}\n"
    )
    config, archive = three_airframe_node(tmp_path, ports, tun_extra=tun_extra)
    return config, ports, archive


def drain(sock: socket.socket) -> list[bytes]:
    got = []
    while True:
        try:
            got.append(sock.recv(4096))
        except (TimeoutError, BlockingIOError):
            return got
        except ConnectionRefusedError:
            continue


def airframes_in(archive: Path) -> set[str]:
    return {event.get("airframe") for event in archive_events(archive)}


def test_plain_frames_with_a_secure_airframes_sysid_are_never_attributed(
    tmp_path: Path, udp_socket: Callable[[], socket.socket]
) -> None:
    config, ports, archive = write_config(tmp_path)
    attacker = udp_socket()
    with running(config) as daemon:
        before = daemon.status()
        fakes = [Airframe(1), Airframe(2)]
        sent = 0
        for _ in range(10):
            for fake in fakes:
                for frame in (fake.heartbeat(), fake.position(), fake.detection()):
                    attacker.sendto(frame, ("127.0.0.1", ports["open"]))
                    sent += 1
        # A genuine OPEN frame after the attack: once it is archived, the attack was read.
        genuine = Airframe(3)
        attacker.sendto(genuine.position(), ("127.0.0.1", ports["open"]))
        wait_until(lambda: "OPEN" in airframes_in(archive), 10, "OPEN's telemetry archived")
        wait_until(
            lambda: (
                daemon.metric("fg_link_frames_rejected_total", link="open", reason="foreign_link")
                == sent
            ),
            5,
            "every impersonating frame counted",
        )
        assert airframes_in(archive) == {"OPEN"}
        after = daemon.status()
        for name in ("TUN", "SIG"):
            old = next(a for a in before["airframes"] if a["airframe"] == name)
            new = next(a for a in after["airframes"] if a["airframe"] == name)
            assert new["active_link"] is None
            assert [link["link"] for link in new["links"]] == [
                link["link"] for link in old["links"]
            ]
            assert all(link["frames"] == 0 for link in new["links"])
        assert daemon.metric("fg_link_frames_total", link="open") == 1
        # Logged, but not per frame: one line for the link and reason within the interval.
        assert len([e for e in daemon.events("frame_rejected") if e["link"] == "open"]) == 1


def test_uplink_goes_sealed_to_the_authenticated_peer_only_and_never_in_plaintext(
    tmp_path: Path, udp_socket: Callable[[], socket.socket]
) -> None:
    config, ports, _archive = write_config(tmp_path)
    genuine, garbage_sender, attacker, gcs = (udp_socket() for _ in range(4))
    seal = sealer("TUN")
    tun = Airframe(1)
    gcs_mav = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    command = bytes(gcs_mav.command_long_encode(1, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0).pack(gcs_mav))
    with running(config) as daemon:
        # The attacker's plain TUN frames reach OPEN's port; a second socket sends garbage
        # (and a plain frame) to the tunnel port; the genuine airframe sends sealed frames.
        attacker.sendto(tun.heartbeat(), ("127.0.0.1", ports["open"]))
        garbage_sender.sendto(b"\x00" * 40, ("127.0.0.1", ports["tun"]))
        garbage_sender.sendto(tun.heartbeat(), ("127.0.0.1", ports["tun"]))
        for _ in range(3):
            genuine.sendto(seal.seal(tun.heartbeat()), ("127.0.0.1", ports["tun"]))
        wait_until(lambda: daemon.status()["airframes"][0]["active_link"] == "tun", 10, "tunnel up")
        gcs.sendto(command, ("127.0.0.1", ports["gcs"]))
        wait_until(lambda: daemon.metric("fg_uplink_sends_total", airframe="TUN") == 1, 5, "uplink")
        sealed = drain(genuine)
        # Downlink copies go to the GCS, not here; what the airframe got is the sealed command.
        assert len(sealed) == 1
        assert sealed[0][:2] == b"F6"
        assert command not in sealed[0]
        assert drain(garbage_sender) == []
        assert drain(attacker) == []
        # Jammed: the tunnel falls silent, the link times out, and the ground station's next
        # command has nowhere to go: refused and counted, never sent in plaintext elsewhere.
        wait_until(
            lambda: daemon.status()["airframes"][0]["active_link"] is None, 10, "tunnel timeout"
        )
        attacker.sendto(tun.heartbeat(), ("127.0.0.1", ports["open"]))
        time.sleep(0.2)
        gcs.sendto(command, ("127.0.0.1", ports["gcs"]))
        wait_until(
            lambda: daemon.metric("fg_uplink_refused_total", airframe="TUN", reason="no_link") == 1,
            5,
            "the refused uplink counted",
        )
        assert drain(attacker) == []
        assert drain(garbage_sender) == []
        assert drain(genuine) == []
        assert daemon.metric("fg_uplink_sends_total", airframe="TUN") == 1


def test_signed_link_uplink_is_signed(
    tmp_path: Path, udp_socket: Callable[[], socket.socket]
) -> None:
    """A ground station's unsigned command leaves on a signed link signed with the key.

    The airframe accepts unsigned RADIO_STATUS (as config/example.yaml does): an attacker's
    unsigned RADIO_STATUS from another port is used, but does not make it the uplink peer.
    """
    config, ports, _archive = write_config(tmp_path)
    config.write_text(
        config.read_text().replace(
            "signing: {key_file:", "signing: {accept_unsigned_msgids: [109], key_file:"
        )
    )
    gcs_port = free_udp_port()
    sig_link = (
        f"    links: [{{uri: 'udp://127.0.0.1:{ports['sig']}', security: signed, name: sig}}]"
    )
    text = config.read_text()
    assert sig_link in text
    passthrough = f"    passthrough: {{uri: 'udp://127.0.0.1:{gcs_port}', uplink: open}}\n"
    config.write_text(text.replace(sig_link, passthrough + sig_link))
    autopilot, gcs, attacker = udp_socket(), udp_socket(), udp_socket()
    fake = mav.MAVLink(None, srcSystem=2, srcComponent=68)
    radio_status = bytes(fake.radio_status_encode(200, 190, 100, 10, 12, 0, 0).pack(fake))
    gcs_mav = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    command = bytes(gcs_mav.command_long_encode(2, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0).pack(gcs_mav))
    with running(config) as daemon:
        # Its signing clock starts now, after the gateway's (see test_restart_replay.py).
        sig = Airframe(2, signing_key=SIGNING_KEY)
        autopilot.sendto(sig.heartbeat(), ("127.0.0.1", ports["sig"]))
        wait_until(
            lambda: daemon.status()["airframes"][1]["active_link"] == "sig", 10, "signed link up"
        )
        attacker.sendto(radio_status, ("127.0.0.1", ports["sig"]))
        wait_until(lambda: daemon.metric("fg_link_frames_total", link="sig") == 2, 5, "accepted")
        gcs.sendto(command, ("127.0.0.1", gcs_port))
        wait_until(lambda: daemon.metric("fg_uplink_sends_total", airframe="SIG") == 1, 5, "sent")
        received = [frame for frame in drain(autopilot) if frame[0] == 0xFD and frame[7] == 76]
        assert drain(attacker) == []
    checker = mav.MAVLink(None)
    checker.signing.secret_key = SIGNING_KEY
    msgs = [checker.parse_char(frame) for frame in received]
    assert len(msgs) == 1
    assert msgs[0] is not None
    assert msgs[0].get_signed()
    assert checker.signing.badsig_count == 0


def test_sealed_frames_replayed_on_another_link_are_refused_and_cannot_win_failover(
    tmp_path: Path, udp_socket: Callable[[], socket.socket]
) -> None:
    """The attacker copies TUN's sealed frames from the radio link to the TCP link, late."""
    config, ports, archive = write_config(tmp_path)
    tcp_port = free_tcp_port()
    text = config.read_text()
    tun_link = (
        f"    links: [{{uri: 'udp://127.0.0.1:{ports['tun']}', security: tunnel, name: tun}}]"
    )
    assert tun_link in text
    config.write_text(
        text.replace(
            tun_link,
            f"    links:\n      - {{uri: 'udp://127.0.0.1:{ports['tun']}', security: tunnel, "
            "name: tun}\n"
            f"      - {{uri: 'tcp://127.0.0.1:{tcp_port}?mode=listen', security: tunnel, "
            "name: tcp, priority: 1}",
        )
    )
    genuine = udp_socket()
    seal, tun = sealer("TUN"), Airframe(1)
    with running(config) as daemon:
        captured = [seal.seal(tun.heartbeat()), seal.seal(tun.detection())]
        for frame in captured:
            genuine.sendto(frame, ("127.0.0.1", ports["tun"]))
        wait_until(lambda: daemon.metric("fg_link_frames_total", link="tun") == 2, 5, "genuine")
        time.sleep(1.2)  # later than any redundant copy, well inside the freshness window
        with socket.create_connection(("127.0.0.1", tcp_port)) as attacker:
            for frame in captured:
                attacker.sendall(frame_for_stream(frame))
            wait_until(
                lambda: (
                    daemon.metric("fg_link_frames_rejected_total", link="tcp", reason="replay") == 2
                ),
                5,
                "the replays refused",
            )
            tun_status = daemon.status()["airframes"][0]
            # The radio link has timed out (0.5 s) by now; the replayed link did not take over.
            assert tun_status["active_link"] != "tcp"
            tcp = next(link for link in tun_status["links"] if link["link"] == "tcp")
            assert tcp["up"] is False
        assert daemon.metric("fg_link_frames_total", link="tcp") == 0
    detections = [e for e in archive_events(archive) if e.get("kind") == "detection"]
    assert len(detections) == 1
