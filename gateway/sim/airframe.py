"""A simulated Fischer 26E that flies a circle and speaks real MAVLink 2 (pymavlink-encoded).

``frames_at`` is pure and deterministic (sim time in, frames out), so tests can compare
what the gateway delivers with what was sent. ``run_udp`` paces it on the event loop's clock
and sends one frame per datagram, sealed in the tunnel when given a ``Sealer``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import anyio
import anyio.abc
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.tunnel import Sealer

__all__ = ["SentPosition", "SimProfile", "SimulatedAirframe", "build_demo_fleet", "run_fleet"]

_EARTH_R_M = 6_371_000.0
_G = 9.80665


@dataclass(frozen=True)
class SimProfile:
    """A deterministic flight: a circle around a centre, and the rates of each message."""

    centre_lat_deg: float = 65.8252  # Boden, Sweden
    centre_lon_deg: float = 21.6886
    radius_m: float = 400.0
    alt_msl_m: float = 250.0
    geoid_sep_m: float = 22.0
    speed_mps: float = 22.0
    position_hz: float = 10.0
    status_hz: float = 2.0
    gps_hz: float = 5.0
    heartbeat_hz: float = 1.0
    battery_wh: float = 600.0
    power_w: float = 355.0


@dataclass(frozen=True)
class SentPosition:
    """A GLOBAL_POSITION_INT as sent, in wire units."""

    time_boot_ms: int
    lat_e7: int
    lon_e7: int
    alt_mm: int


@dataclass
class _Schedule:
    period_s: float
    next_s: float = 0.0


class SimulatedAirframe:
    """One airframe: its MAVLink encoder, flight profile and message schedule."""

    def __init__(
        self, sysid: int, profile: SimProfile | None = None, *, phase_rad: float = 0.0
    ) -> None:
        self.sysid = sysid
        self.profile = profile or SimProfile()
        self.phase_rad = phase_rad
        self._mav = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
        p = self.profile
        self._schedules: dict[str, _Schedule] = {
            "heartbeat": _Schedule(1.0 / p.heartbeat_hz),
            "position": _Schedule(1.0 / p.position_hz),
            "gps": _Schedule(1.0 / p.gps_hz),
            "status": _Schedule(1.0 / p.status_hz),
        }
        self.sent_positions: list[SentPosition] = []
        self.frames_sent = 0

    def _state(self, t_s: float) -> tuple[float, float, float, float]:
        """(lat, lon, track angle rad, bank angle rad) at sim time ``t_s``."""
        p = self.profile
        omega = p.speed_mps / p.radius_m
        theta = self.phase_rad + omega * t_s
        north, east = p.radius_m * math.cos(theta), p.radius_m * math.sin(theta)
        lat = p.centre_lat_deg + math.degrees(north / _EARTH_R_M)
        lon = p.centre_lon_deg + math.degrees(
            east / (_EARTH_R_M * math.cos(math.radians(p.centre_lat_deg)))
        )
        track = theta + math.pi / 2  # counter-clockwise seen from above is clockwise in NED
        bank = math.atan(p.speed_mps**2 / (p.radius_m * _G))
        return lat, lon, track % (2 * math.pi), bank

    def _encode(self, msg: mav.MAVLink_message) -> bytes:
        frame = bytes(msg.pack(self._mav))
        # pack() does not advance the sequence number (send() would); receivers count gaps.
        self._mav.seq = (self._mav.seq + 1) % 256
        return frame

    def frames_at(self, t_s: float) -> list[bytes]:
        """The frames due at sim time ``t_s`` (each schedule fires once its period passed)."""
        frames: list[bytes] = []
        for name, schedule in self._schedules.items():
            if t_s + 1e-9 >= schedule.next_s:
                schedule.next_s += schedule.period_s
                frames.extend(getattr(self, f"_{name}")(t_s))
        return frames

    def _heartbeat(self, _t_s: float) -> list[bytes]:
        base_mode = mav.MAV_MODE_FLAG_SAFETY_ARMED | mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        msg = self._mav.heartbeat_encode(
            mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, 15,
            mav.MAV_STATE_ACTIVE,
        )  # fmt: skip
        return [self._encode(msg)]

    def _position(self, t_s: float) -> list[bytes]:
        p = self.profile
        lat, lon, track, bank = self._state(t_s)
        boot_ms = int(t_s * 1000)
        lat_e7, lon_e7 = round(lat * 1e7), round(lon * 1e7)
        alt_mm = round(p.alt_msl_m * 1000)
        vx = round(p.speed_mps * math.cos(track) * 100)
        vy = round(p.speed_mps * math.sin(track) * 100)
        hdg = round(math.degrees(track) * 100) % 36000
        self.sent_positions.append(SentPosition(boot_ms, lat_e7, lon_e7, alt_mm))
        gpi = self._mav.global_position_int_encode(
            boot_ms, lat_e7, lon_e7, alt_mm, alt_mm - 100_000, vx, vy, 0, hdg
        )
        att = self._mav.attitude_encode(boot_ms, -bank, 0.05, _wrap_pi(track), 0.0, 0.0, 0.055)
        return [self._encode(gpi), self._encode(att)]

    def _gps(self, t_s: float) -> list[bytes]:
        p = self.profile
        lat, lon, track, _ = self._state(t_s)
        alt_mm = round(p.alt_msl_m * 1000)
        gps = self._mav.gps_raw_int_encode(
            int(t_s * 1e6), 3, round(lat * 1e7), round(lon * 1e7), alt_mm, 80, 120,
            round(p.speed_mps * 100), round(math.degrees(track) * 100) % 36000, 17,
            alt_ellipsoid=alt_mm + round(p.geoid_sep_m * 1000), h_acc=1200, v_acc=2000,
        )  # fmt: skip
        hud = self._mav.vfr_hud_encode(
            p.speed_mps, p.speed_mps, round(math.degrees(track)) % 360, 55, p.alt_msl_m, 0.0
        )
        return [self._encode(gps), self._encode(hud)]

    def _status(self, t_s: float) -> list[bytes]:
        p = self.profile
        used_wh = p.power_w * t_s / 3600.0
        remaining = max(0, round(100 * (1 - used_wh / p.battery_wh)))
        voltage_mv, current_ca = 22_200, round(p.power_w / 22.2 * 100)
        status = self._mav.sys_status_encode(
            0, 0, 0, 300, voltage_mv, current_ca, remaining, 0, 0, 0, 0, 0, 0
        )
        left_s = round(max(0.0, p.battery_wh - used_wh) / p.power_w * 3600)
        battery = self._mav.battery_status_encode(
            0, 0, 0, 2500, [3700] * 6 + [65535] * 4, current_ca, -1,
            round(used_wh * 36), remaining, time_remaining=left_s,
        )  # fmt: skip
        return [self._encode(status), self._encode(battery)]

    async def run_udp(
        self,
        host: str,
        port: int,
        *,
        duration_s: float | None = None,
        speed: float = 1.0,
        sealer: Sealer | None = None,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Fly and send frames as UDP datagrams to host:port until ``duration_s`` of sim time."""
        step_s = 1.0 / max(self.profile.position_hz, self.profile.gps_hz, 1.0) / 2
        async with await anyio.create_connected_udp_socket(
            remote_host=host, remote_port=port
        ) as sock:
            task_status.started()
            start = anyio.current_time()
            t_s = 0.0
            while duration_s is None or t_s <= duration_s:
                for frame in self.frames_at(t_s):
                    await sock.send(sealer.seal(frame) if sealer else frame)
                    self.frames_sent += 1
                t_s += step_s
                delay = start + t_s / speed - anyio.current_time()
                await anyio.sleep(max(delay, 0.0))


def _wrap_pi(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def build_demo_fleet(n: int = 2) -> list[SimulatedAirframe]:
    """``n`` airframes (sysids 1..n) on neighbouring circles around Boden."""
    return [
        SimulatedAirframe(
            i + 1,
            SimProfile(centre_lat_deg=65.8252 + 0.01 * i, centre_lon_deg=21.6886 + 0.02 * i),
            phase_rad=i * 2.0,
        )
        for i in range(n)
    ]


async def run_fleet(
    airframes: Sequence[SimulatedAirframe],
    host: str,
    ports: Sequence[int],
    *,
    duration_s: float | None = None,
    speed: float = 1.0,
    sealers: Sequence[Sealer | None] | None = None,
    task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
) -> None:
    """Run several simulated airframes concurrently, airframe ``i`` sending to ``ports[i]``."""
    seal = list(sealers) if sealers is not None else [None] * len(airframes)
    async with anyio.create_task_group() as tg:
        for airframe, port, sealer in zip(airframes, ports, seal, strict=True):
            await tg.start(
                lambda a=airframe, p=port, s=sealer, task_status=anyio.TASK_STATUS_IGNORED: (
                    a.run_udp(
                        host,
                        p,
                        duration_s=duration_s,
                        speed=speed,
                        sealer=s,
                        task_status=task_status,
                    )
                )
            )
        task_status.started()
