"""Secure links end to end: tunnel, signing, failover with de-duplication, passthrough."""

from __future__ import annotations

import hashlib
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import anyio
import pytest
from daemon_support import free_udp_port
from pymavlink.dialects.v20 import ardupilotmega as mav
from structlog.testing import capture_logs

from gateway.app import Gateway
from gateway.cli import main
from gateway.config import Config
from gateway.errors import ConfigError
from gateway.events import LinkState, Telemetry
from gateway.fleet.deframe import frame_for_stream
from gateway.fleet.security.keys import load_day_keys, read_credential, read_key_file
from gateway.fleet.security.signing import mavlink_timestamp_now
from gateway.fleet.security.tunnel import DayKeys, Sealer, TunnelOpener, derive_day_key
from gateway.sim.airframe import SimulatedAirframe
from gateway.testing import MemorySink, eventually


def write_key(path: Path, data: bytes, mode: int = 0o600) -> Path:
    path.write_text(data.hex() + "\n")
    path.chmod(mode)
    return path


def make_config(links: list[dict[str, Any]], **extra: Any) -> Config:
    airframe = {"id": "F26E-001", "sysid": 1, "links": links, **extra.pop("airframe", {})}
    return Config.model_validate(
        {
            "gateway": {"shutdown_deadline_s": 1},
            "health": {"enabled": False},
            "airframes": [airframe],
            "sinks": [{"name": "mem", "type": "memory"}],
            "routes": [{"sinks": ["mem"]}],
            **extra,
        }
    )


def port_of(gateway: Gateway, index: int = 0) -> int:
    return int(list(gateway.fleet.links.values())[index].local_port)  # type: ignore[attr-defined]


def positions(sink: MemorySink) -> list[tuple[float, float]]:
    return [
        (e.position.lat_deg, e.position.lon_deg)
        for e in sink.events
        if isinstance(e, Telemetry) and e.position is not None
    ]


class TestTunnel:
    """Telemetry sealed by an airframe holding only its day keys reaches the sinks."""

    @pytest.mark.anyio
    async def test_sealed_telemetry_arrives_and_forgeries_are_counted(self, tmp_path: Path) -> None:
        master = bytes(range(32))
        master_file = write_key(tmp_path / "master.key", master)
        assert main(
            ["keys", "derive", "--master", str(master_file), "--airframe", "F26E-001",
             "--from", datetime.now(UTC).date().isoformat(), "--days", "2",
             "--out", str(tmp_path / "days")]
        ) == 0  # fmt: skip
        day_keys = load_day_keys(tmp_path / "days", "F26E-001")
        assert len(day_keys) == 2
        assert all(key != master and master.hex() not in key.hex() for key in day_keys.values())
        config = make_config(
            [{"uri": "udp://127.0.0.1:0", "security": "tunnel"}],
            tunnel={"master_key_file": str(master_file)},
        )
        mem = MemorySink("mem")
        gateway = Gateway(config, sinks={"mem": mem})
        sim = SimulatedAirframe(1)
        sealer = Sealer("F26E-001", DayKeys(keys=day_keys), lambda: datetime.now(UTC))
        with capture_logs() as logs, anyio.fail_after(20):
            async with anyio.create_task_group() as tg:
                await tg.start(gateway.run)
                port = port_of(gateway)
                async with await anyio.create_connected_udp_socket(
                    remote_host="127.0.0.1", remote_port=port
                ) as sock:
                    plain = sim.frames_at(0.0)[0]
                    await sock.send(plain)  # unsealed MAVLink on a tunnel link
                    sealed = sealer.seal(plain)
                    await sock.send(sealed)
                    await sock.send(sealed)  # replayed
                    fresh = sealer.seal(plain)
                    await sock.send(fresh[:-1] + bytes([fresh[-1] ^ 1]))  # forged tag
                await sim.run_udp("127.0.0.1", port, duration_s=1.0, speed=10.0, sealer=sealer)
                final = sim.sent_positions[-1]
                await eventually(lambda: (final.lat_e7 / 1e7, final.lon_e7 / 1e7) in positions(mem))
                gateway.shutdown()
        rejected = gateway.instruments.link_rejected
        label = next(iter(gateway.fleet.links.values())).label
        latency = gateway.instruments.link_latency.labels("F26E-001", label)
        assert latency.count > 0
        assert 0 <= latency.sum / latency.count < 1.0  # loopback, one clock
        (link,) = gateway.status()["airframes"][0]["links"]
        assert link["latency_s"] is not None
        assert rejected.labels(label, "malformed").value == 1
        assert rejected.labels(label, "replay").value == 1
        assert rejected.labels(label, "auth").value == 1
        text = repr(logs)
        assert master.hex() not in text
        assert all(key.hex() not in text for key in day_keys.values())
        assert any(log["event"] == "frame_rejected" for log in logs)

    def test_group_readable_master_key_is_refused(self, tmp_path: Path) -> None:
        path = write_key(tmp_path / "master.key", bytes(32), mode=0o640)
        with pytest.raises(ConfigError, match="mode is 640"):
            read_key_file(path)

    def test_a_key_of_the_wrong_length_names_both_forms(self, tmp_path: Path) -> None:
        """A passphrase written where its SHA-256 belongs: the message says what fits."""
        path = write_key(tmp_path / "gcs.key", b"a-passphrase")
        with pytest.raises(ConfigError, match=r"exactly 32 key bytes \(raw, or written as 64 hex"):
            read_key_file(path, exact=True)

    def test_tunnel_link_without_a_master_key_is_a_config_error(self, tmp_path: Path) -> None:
        cfg = tmp_path / "c.yaml"
        cfg.write_text(
            "airframes:\n  - id: A\n    sysid: 1\n    links:\n"
            "      - {uri: 'udp://127.0.0.1:0', security: tunnel}\n"
        )
        assert main(["check-config", str(cfg)]) == 2


class TestSigning:
    """Signed links accept frames signed with the airframe's key and nothing else."""

    @pytest.mark.anyio
    async def test_signed_frames_pass_unsigned_and_forged_do_not(self, tmp_path: Path) -> None:
        key = hashlib.sha256(b"airframe 1 signing key").digest()
        config = make_config(
            [{"uri": "udp://127.0.0.1:0", "security": "signed"}],
            airframe={"signing": {"key_file": str(write_key(tmp_path / "s.key", key))}},
        )
        mem = MemorySink("mem")
        gateway = Gateway(config, sinks={"mem": mem})

        def encoder(secret: bytes | None, link_id: int = 1) -> mav.MAVLink:
            m = mav.MAVLink(None, srcSystem=1, srcComponent=1)
            if secret is not None:
                m.signing.secret_key = secret
                m.signing.link_id = link_id
                m.signing.sign_outgoing = True
                m.signing.timestamp = mavlink_timestamp_now(time.time())
            return m

        def position(m: mav.MAVLink, lat_e7: int) -> bytes:
            msg = m.global_position_int_encode(0, lat_e7, 200000000, 1000, 0, 0, 0, 0, 0)
            return bytes(msg.pack(m))

        with anyio.fail_after(20):
            async with anyio.create_task_group() as tg:
                await tg.start(gateway.run)
                async with await anyio.create_connected_udp_socket(
                    remote_host="127.0.0.1", remote_port=port_of(gateway)
                ) as sock:
                    await sock.send(position(encoder(None), 600000001))
                    await sock.send(position(encoder(bytes(32)), 600000002))
                    await sock.send(position(encoder(key), 600000003))
                await eventually(lambda: bool(positions(mem)))
                gateway.shutdown()
        assert positions(mem) == [(60.0000003, 20.0)]
        (link,) = gateway.status()["links"]
        assert link["security"] == "signed"
        (airframe,) = gateway.status()["airframes"]
        assert airframe["signing"] == {
            "signed": 1,
            "unsigned": 1,
            "bad_signature": 1,
            "replayed": 0,
        }


class TestFailover:
    """Two links carrying the same frames: delivered once; cut the primary, it carries on."""

    @pytest.mark.anyio
    async def test_duplicates_suppressed_and_failover_within_a_second(self) -> None:
        config = make_config(
            [
                {"uri": "udp://127.0.0.1:0", "security": "unsecured", "name": "starlink"},
                {
                    "uri": f"udp://127.0.0.1:{free_udp_port()}",
                    "security": "unsecured",
                    "name": "sdr",
                    "priority": 1,
                },
            ],
            airframe={"link_timeout_s": 0.4, "failback_hold_s": 0.5},
        )
        mem = MemorySink("mem")
        gateway = Gateway(config, sinks={"mem": mem})
        sim = SimulatedAirframe(1)
        with anyio.fail_after(20):
            async with anyio.create_task_group() as tg:
                await tg.start(gateway.run)
                primary = await anyio.create_connected_udp_socket(
                    remote_host="127.0.0.1", remote_port=port_of(gateway, 0)
                )
                secondary = await anyio.create_connected_udp_socket(
                    remote_host="127.0.0.1", remote_port=port_of(gateway, 1)
                )
                t, sent_both, total = 0.0, 0, 0
                start = anyio.current_time()
                cut_at = None
                while t < 2.0:
                    for frame in sim.frames_at(t):
                        if t < 1.0:
                            await primary.send(frame)
                            sent_both += 1
                        elif cut_at is None:
                            cut_at = anyio.current_time()
                        await secondary.send(frame)
                        total += 1
                    t += 0.05
                    await anyio.sleep(max(0.0, start + t / 2 - anyio.current_time()))
                final = sim.sent_positions[-1]
                await eventually(lambda: (final.lat_e7 / 1e7, final.lon_e7 / 1e7) in positions(mem))
                await eventually(lambda: gateway.fleet.ingest.active_link("F26E-001") == "sdr")
                failover_s = anyio.current_time() - (cut_at or 0.0)
                await primary.aclose()
                await secondary.aclose()
                gateway.shutdown()
        ignored = gateway.instruments.link_ignored
        duplicates = (
            ignored.labels("sdr", "duplicate").value + ignored.labels("starlink", "duplicate").value
        )
        assert duplicates == sent_both
        # At most one Telemetry per frame the simulator made: none was delivered twice.
        assert 0 < gateway.instruments.events.labels("telemetry").value <= total
        assert failover_s < 1.0
        states = [(e.link, e.is_up, e.is_active) for e in mem.events if isinstance(e, LinkState)]
        assert ("starlink", False, False) in states
        assert ("sdr", True, True) in states


class TestStreamsAndOutbound:
    """The tunnel over a TCP stream link, and outbound frames sealed the same way."""

    @pytest.mark.anyio
    async def test_tunnel_over_tcp_resynchronises_after_garbage(self, tmp_path: Path) -> None:
        master_file = write_key(tmp_path / "master.key", bytes(range(32)))
        config = make_config(
            [{"uri": "tcp://127.0.0.1:0?mode=listen", "security": "tunnel"}],
            tunnel={"master_key_file": str(master_file)},
        )
        mem = MemorySink("mem")
        gateway = Gateway(config, sinks={"mem": mem})
        sim = SimulatedAirframe(1)
        sealer = Sealer("F26E-001", DayKeys(master=bytes(range(32))), lambda: datetime.now(UTC))
        with anyio.fail_after(20):
            async with anyio.create_task_group() as tg:
                await tg.start(gateway.run)
                port = next(iter(gateway.fleet.links.values())).local_port  # type: ignore[attr-defined]
                async with await anyio.connect_tcp("127.0.0.1", port) as stream:
                    t = 0.0
                    for _ in range(20):
                        chunk = b"\x00\x30F6garbage" + b"".join(
                            frame_for_stream(sealer.seal(f)) for f in sim.frames_at(t)
                        )
                        await stream.send(chunk)
                        t += 0.1
                    final = sim.sent_positions[-1]
                    await eventually(
                        lambda: (final.lat_e7 / 1e7, final.lon_e7 / 1e7) in positions(mem)
                    )
                gateway.shutdown()

    @pytest.mark.anyio
    async def test_outbound_frames_are_sealed_for_the_airframe(self, tmp_path: Path) -> None:
        master = bytes(range(32))
        config = make_config(
            [{"uri": "udp://127.0.0.1:0", "security": "tunnel"}],
            tunnel={"master_key_file": str(write_key(tmp_path / "m.key", master))},
        )
        gateway = Gateway(config, sinks={"mem": MemorySink("mem")})
        airframe_keys = DayKeys(
            keys={
                ("F26E-001", d): derive_day_key(master, "F26E-001", d)
                for d in (datetime.now(UTC).date(),)
            }
        )
        sealer = Sealer("F26E-001", airframe_keys, lambda: datetime.now(UTC))
        opener = TunnelOpener(airframe_keys, frozenset({"F26E-001"}), lambda: datetime.now(UTC))
        gcs = mav.MAVLink(None, srcSystem=255, srcComponent=190)
        command = bytes(gcs.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs))
        with anyio.fail_after(20):
            async with anyio.create_task_group() as tg:
                await tg.start(gateway.run)
                async with await anyio.create_connected_udp_socket(
                    remote_host="127.0.0.1", remote_port=port_of(gateway)
                ) as sock:
                    await sock.send(sealer.seal(SimulatedAirframe(1).frames_at(0.0)[0]))
                    await eventually(lambda: gateway.fleet.is_linked("F26E-001"))
                    await gateway.fleet.send("F26E-001", command)
                    sealed = await sock.receive()
                gateway.shutdown()
        assert command not in sealed
        assert opener.open_frame(sealed, "uplink").payload == command


def test_master_key_from_a_systemd_credential(tmp_path: Path) -> None:
    (tmp_path / "tunnel-master").write_text(bytes(range(32)).hex())
    assert read_credential("tunnel-master", {"CREDENTIALS_DIRECTORY": str(tmp_path)}) == bytes(
        range(32)
    )
    with pytest.raises(ConfigError, match="CREDENTIALS_DIRECTORY"):
        read_credential("tunnel-master", {})
