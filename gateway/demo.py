"""``fischer-gateway demo``: the brigade operation at Boden, end to end on loopback.

The gateway runs on its embedded defaults (``gateway/defaults/demo.yaml``) beside three
stand-ins for its peers, all real sockets on 127.0.0.1: the simulator playing the shipped
``brigade`` scenario (two airframes in the AES-256-GCM tunnel, friendly platoons reporting
by CoT), a simulated GUTE II battery (HTTPS, a demo-only CA and client certificate made on
each start) and a CoT receiver standing in for ATAK. The story is printed as it happens,
from real events: the gateway's ``story`` console sink tells what reached the bus (friendly
units registered, detections ingested, fused tracks, deconfliction and cues), and the
stand-ins tell what was published to them. The demo says "deconfliction clear", never that
an engagement is authorised: that is the battery operator's decision, and no part of the
gateway takes it.
"""

from __future__ import annotations

import os
import secrets
import socket
import sys
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from datetime import timedelta
from importlib.resources import files
from pathlib import Path
from typing import Any

import anyio
import anyio.abc
from defusedxml import ElementTree

from gateway.app import Gateway
from gateway.clock import utc_now
from gateway.config import Config
from gateway.configfile import load_config_text
from gateway.fleet.security.keys import read_key_file
from gateway.fleet.security.tunnel import DayKeys, Sealer, derive_day_key
from gateway.sim.battery import SimulatedBattery
from gateway.sim.pki import make_demo_pki
from gateway.sim.runner import play_scenario
from gateway.sim.scenario import Scenario, load_scenario

__all__ = ["Demo", "prepare_demo"]

#: After the scenario ends: time for the last cues to be delivered before the demo stops.
DRAIN_S = 4.0


def say(line: str) -> None:
    """One line of the story, stamped with the UTC time."""
    sys.stdout.write(f"{utc_now():%H:%M:%S}Z {line}\n")
    sys.stdout.flush()


@dataclass
class Demo:
    """Everything the demo runs: the gateway's config and the peers' sockets."""

    config: Config
    scenario: Scenario
    battery: SimulatedBattery
    atak: socket.socket
    cot_port: int
    link_port: int
    speed: float

    def sealers(self) -> list[Sealer | None]:
        """Each simulated airframe gets only its own day keys (today and tomorrow)."""
        assert self.config.tunnel.master_key_file is not None  # noqa: S101 - set by prepare
        master = read_key_file(self.config.tunnel.master_key_file)
        today = utc_now().date()
        return [
            Sealer(
                airframe.id,
                DayKeys(
                    keys={
                        (airframe.id, day): derive_day_key(master, airframe.id, day)
                        for day in (today, today + timedelta(days=1))
                    }
                ),
                utc_now,
            )
            for airframe in self.scenario.airframes
        ]

    def player(self, gateway: Gateway) -> Callable[[], Coroutine[Any, Any, None]]:
        """The coroutine that plays the operation beside ``gateway`` and then stops it."""

        async def play() -> None:
            for processor in gateway.processors.values():
                for battery in getattr(processor.processor, "batteries", ()):
                    say(
                        f"battery registered: GUTE II {battery.id} at"
                        f" {battery.position.lat_deg:.4f} N {battery.position.lon_deg:.4f} E,"
                        f" effectors {', '.join(sorted(battery.effectors))}"
                    )
            say(
                f"scenario {self.scenario.name}: {self.scenario.description}"
                f" ({self.scenario.duration_s / self.speed:.0f} s at speed {self.speed:g})"
            )
            async with anyio.create_task_group() as tg:
                await tg.start(self.battery.serve)
                tg.start_soon(self._atak)
                link = next(iter(gateway.fleet.links.values()))
                port = getattr(link, "local_port", 0) or self.link_port  # --udp-port 0: bound now
                await play_scenario(
                    self.scenario,
                    "127.0.0.1",
                    port,
                    cot=("127.0.0.1", self.cot_port),
                    speed=self.speed,
                    sealers=self.sealers(),
                )
                await anyio.sleep(DRAIN_S)
                say("scenario complete; stopping")
                gateway.shutdown()
                tg.cancel_scope.cancel()

        return play

    async def _atak(self) -> None:
        """The ATAK stand-in: tells the first CoT event of each uid it receives."""
        seen: set[str] = set()
        udp = await anyio.abc.UDPSocket.from_socket(self.atak)
        async with udp:
            async for data, _ in udp:
                try:
                    root = ElementTree.fromstring(data)
                except ElementTree.ParseError:
                    continue
                uid, kind = root.get("uid", ""), root.get("type", "")
                if uid in seen or len(seen) > 10_000:
                    continue
                seen.add(uid)
                port = self.atak.getsockname()[1]
                say(f"published: CoT to ATAK (udp 127.0.0.1:{port}) {uid} {kind}")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _on_handoff(document: dict[str, Any]) -> None:
    status = document.get("status") or "active"
    if status != "active":  # superseded or withdrawn: the battery drops the cue
        say(
            f"published: GUTE II battery {(document.get('battery') or {}).get('id')} received cue"
            f" {document.get('handoff_id')} revision {document.get('revision')} over HTTPS:"
            f" {status}: {document.get('note') or '-'}"
        )
        return
    check = document.get("deconfliction") or {}
    asks = str(document.get("operator_authorisation_required")).lower()
    verdict = "deconfliction clear" if check.get("clear") else "deconfliction NOT clear"
    say(
        f"published: GUTE II battery {(document.get('battery') or {}).get('id')} received cue"
        f" {document.get('handoff_id')} revision {document.get('revision')} over HTTPS:"
        f" {verdict}, recommended {document.get('recommended_effector') or 'none'},"
        f" operator_authorisation_required {asks}"
    )


def prepare_demo(
    archive: Path | None,
    *,
    udp_port: int | None = None,
    health_port: int | None = None,
    speed: float = 1.0,
) -> Demo:
    """The demo's config and peers, with its files under ``archive``'s folder."""
    text = files("gateway").joinpath("defaults/demo.yaml").read_text(encoding="utf-8")
    data = load_config_text(text, "demo.yaml").model_dump(mode="json")
    archive = archive or Path("fischer-demo/archive.jsonl")
    base = archive.parent
    base.mkdir(parents=True, exist_ok=True)
    # 0 asks for any free port (suites running side by side), not the default.
    link_port = 14550 if udp_port is None else (udp_port or _free_udp_port())
    for airframe in data["airframes"]:
        for link in airframe["links"]:
            link["uri"] = f"udp://127.0.0.1:{link_port}"
    if health_port is not None:
        data["health"]["port"] = health_port
    # The demo's tunnel master key lives next to its archive, created on first run.
    master = base / "demo-master.key"
    if not master.exists():
        fd = os.open(master, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as handle:
            handle.write(secrets.token_hex(32) + "\n")
    data["tunnel"]["master_key_file"] = str(master)
    # Durable events wait on disk next to the archive, as on a real node.
    data["spool"]["path"] = str(base / "spool.db")
    pki = make_demo_pki(base / "pki")
    battery = SimulatedBattery(pki, _on_handoff)
    atak = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    atak.bind(("127.0.0.1", 0))
    cot_port = _free_udp_port()
    data["sources"][0]["uri"] = f"udp://127.0.0.1:{cot_port}"
    for processor in data["processors"]:
        if processor["type"] == "fusion":
            # Played ``speed`` times faster, everything moves that much faster on the wire.
            processor.setdefault("options", {})["speed_scale"] = speed
    for sink in data["sinks"]:
        options = sink["options"]
        if sink["type"] == "jsonl":
            options["path"] = str(archive)
        elif sink["type"] == "gute2":
            options["url"] = f"https://127.0.0.1:{battery.port}/gute2/handoffs"
            options.update(
                ca_file=str(pki.ca_file),
                cert_file=str(pki.client_cert),
                key_file=str(pki.client_key),
            )
        elif sink["type"] == "cot":
            options["destinations"] = [f"udp://127.0.0.1:{atak.getsockname()[1]}"]
    return Demo(
        config=Config.model_validate(data),
        scenario=load_scenario("brigade"),
        battery=battery,
        atak=atak,
        cot_port=cot_port,
        link_port=link_port,
        speed=speed,
    )
