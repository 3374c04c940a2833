"""``fischer-gateway demo``: the brigade operation at Boden, its ten steps end to end on loopback.

The gateway runs on its embedded defaults (``gateway/defaults/demo.yaml``) beside stand-ins
for every peer of the operation, all real sockets on 127.0.0.1 (``gateway/sim/``): the
simulator playing the shipped ``brigade`` scenario (two airframes in the AES-256-GCM
tunnel, friendly platoons reporting by CoT), a GUTE II battery and an SLB server (HTTPS with
client certificates), a SWECCIS server (TLS, length-framed FAS documents), a Ra 180 radio
gateway (UDP; the Swedish WAV when espeak-ng is installed), an ATAK device (CoT over UDP)
and a JAS 39 reporting itself by NFFI over TLS. The certificates come from a demo-only CA
made with ``cryptography`` on each start. Each stand-in parses what it received, and the
``Narrator`` tells the operation's ten steps, each once and in order, as the peer saw it.
The gateway's JSON logs go to ``gateway.log`` beside the archive, not between the story's
lines. The demo says "deconfliction clear", never that an engagement is authorised: that
is the battery operator's decision, and no part of the gateway takes it.
"""

from __future__ import annotations

import os
import secrets
import shutil
import socket
import ssl
import sys
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass
from datetime import timedelta
from importlib.resources import files
from pathlib import Path
from typing import Any, TextIO

import anyio
import structlog

from gateway.app import Gateway
from gateway.clock import utc_now
from gateway.config import Config
from gateway.configfile import load_config_text
from gateway.events import Event, EventKind
from gateway.fleet.security.keys import read_key_file
from gateway.fleet.security.tunnel import DayKeys, Sealer, derive_day_key
from gateway.ops.logsetup import configure_logging
from gateway.sim.atak import SimulatedAtak
from gateway.sim.battery import SimulatedBattery
from gateway.sim.jas39 import fly_jas39
from gateway.sim.narrator import Narrator
from gateway.sim.pki import DemoPki, make_demo_pki
from gateway.sim.ra180 import SimulatedRadioGateway
from gateway.sim.runner import play_scenario
from gateway.sim.scenario import Scenario, load_scenario
from gateway.sim.slb import SimulatedSlb
from gateway.sim.sweccis import SimulatedSweccis

__all__ = ["Demo", "StdoutStory", "StorySink", "prepare_demo"]

log = structlog.get_logger(__name__)

#: After the scenario ends: time for the last cues to be delivered before the demo stops.
DRAIN_S = 4.0
#: How long the NFFI source's port is waited for before the JAS 39 gives up.
_LISTEN_WAIT_S = 10.0


class StdoutStory:
    """Writes the story's lines to stdout; once its reader has gone, stops the demo quietly."""

    def __init__(self) -> None:
        self.on_closed: Callable[[], None] = lambda: None
        self.closed = False

    def __call__(self, line: str) -> None:
        """Write ``line`` and flush."""
        if self.closed:
            return
        try:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()
        except BrokenPipeError:  # `demo | head`: the reader has what it wanted
            self.closed = True
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
            self.on_closed()


class StorySink:
    """The demo's story sink: hands every event routed to it to the ``Narrator``."""

    def __init__(self, name: str, narrator: Narrator) -> None:
        self.name = name
        self._narrator = narrator

    @property
    def kinds(self) -> frozenset[EventKind]:
        """What the story tells of: friendly units, detections, tracks and cues."""
        return frozenset(
            {EventKind.BLUE_FORCE, EventKind.DETECTION, EventKind.TRACK, EventKind.HANDOFF}
        )

    async def open(self) -> None:
        """Nothing to open."""

    async def send(self, batch: Sequence[Event]) -> None:
        """Tell the narrator of each event."""
        for event in batch:
            self._narrator.event(event)

    async def aclose(self) -> None:
        """Nothing to close."""


@dataclass
class Demo:
    """Everything the demo runs: the gateway's config, the stand-ins and the narrator."""

    config: Config
    scenario: Scenario
    pki: DemoPki
    narrator: Narrator
    story: StdoutStory
    battery: SimulatedBattery
    slb: SimulatedSlb
    sweccis: SimulatedSweccis
    radio: SimulatedRadioGateway
    atak: SimulatedAtak
    cot_port: int
    link_port: int
    speed: float
    log_file: Path
    log_stream: TextIO
    archive: Path

    @property
    def sinks(self) -> dict[str, StorySink]:
        """The sinks the demo supplies itself, by config name."""
        return {"story": StorySink("story", self.narrator)}

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
            try:
                await run()
            except anyio.get_cancelled_exc_class():
                # --duration, a signal or a closed stdout stopped the gateway first.
                missing = self.narrator.missing()
                if missing:
                    self.narrator.say(
                        f"stopped before the operation ended; not reached: {', '.join(missing)}"
                    )
                raise

        async def run() -> None:
            self.story.on_closed = gateway.shutdown
            self._opening()
            await self._map_address(gateway)
            for processor in gateway.processors.values():
                for battery in getattr(processor.processor, "batteries", ()):
                    self.narrator.battery(
                        battery.id,
                        battery.position,
                        sorted(battery.effectors),
                        f"https://127.0.0.1:{self.battery.port}/gute2/handoffs",
                    )
            async with anyio.create_task_group() as tg:
                for peer in (self.battery, self.slb, self.sweccis, self.radio, self.atak):
                    await tg.start(peer.serve)
                tg.start_soon(self._jas39, gateway)
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
                missing = self.narrator.missing()
                if missing:
                    self.narrator.say(f"not confirmed by its peer: {', '.join(missing)}")
                self.narrator.say(f"scenario complete; stopping (logs in {self.log_file})")
                gateway.shutdown()
                tg.cancel_scope.cancel()

        return play

    def _opening(self) -> None:
        say = self.narrator.say
        say(
            f"scenario {self.scenario.name}: {self.scenario.description}"
            f" ({self.scenario.duration_s / self.speed:.0f} s at speed {self.speed:g})"
        )
        say(
            f"the gateway's JSON logs: {self.log_file}; its archive: {self.archive}; the"
            f" peers: stand-ins on 127.0.0.1 with a demo CA in {self.pki.ca_file.parent}"
        )
        if self.radio.voice_directory is None:
            say("voice: espeak-ng is not installed, so the Ra 180 step has no Swedish WAV")

    async def _map_address(self, gateway: Gateway) -> None:
        """Say where the live map is, once its sink listens (the sink binds as it opens)."""
        runner = gateway.runners.get("map")
        if runner is None:
            return
        url = None
        with anyio.move_on_after(_LISTEN_WAIT_S):
            while url is None:
                url = getattr(runner.sink, "url", None)
                if url is None:
                    await anyio.sleep(0.05)  # a poll: the sink offers no event for it
        if url is not None:
            self.narrator.say(f"the live map: {url} (open it in a browser on this machine)")

    async def _jas39(self, gateway: Gateway) -> None:
        port = 0
        with anyio.move_on_after(_LISTEN_WAIT_S):
            while not port:
                port = next((int(getattr(s, "local_port", 0)) for s in gateway.sources
                             if s.name == "nffi"), 0)  # fmt: skip
                if not port:
                    await anyio.sleep(0.05)
        if not port:
            log.warning("demo_jas39_grounded", reason="the NFFI source is not listening")
            return
        try:
            await fly_jas39(
                "127.0.0.1", port, self.pki, speed=self.speed, on_sent=self.narrator.jas39_sent
            )
        except (OSError, ssl.SSLError, anyio.BrokenResourceError, anyio.EndOfStream) as exc:
            log.warning("demo_jas39_lost", error=str(exc) or type(exc).__name__)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _log_to(path: Path) -> TextIO:
    """Send the gateway's JSON logs to ``path`` (appended), away from the story on stdout."""
    stream = path.open("a", encoding="utf-8")
    configure_logging("info", stream=stream)
    return stream


def prepare_demo(
    archive: Path | None,
    *,
    udp_port: int | None = None,
    health_port: int | None = None,
    speed: float = 1.0,
) -> Demo:
    """The demo's config, stand-ins and narrator, with its files under ``archive``'s folder.

    From here on the gateway's logs go to ``gateway.log`` in that folder.
    """
    text = files("gateway").joinpath("defaults/demo.yaml").read_text(encoding="utf-8")
    data = load_config_text(text, "demo.yaml").model_dump(mode="json")
    archive = archive or Path("fischer-demo/archive.jsonl")
    base = archive.parent
    base.mkdir(parents=True, exist_ok=True)
    log_file = base / "gateway.log"
    log_stream = _log_to(log_file)
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
    scenario = load_scenario("brigade")
    story = StdoutStory()
    voice = base / "ra180-voice" if shutil.which("espeak-ng") else None
    narrator = Narrator(story, blue_units=len(scenario.blue_forces), voice=voice is not None)
    battery = SimulatedBattery(pki, narrator.cue_received)
    slb = SimulatedSlb(pki, narrator.slb_item)
    sweccis = SimulatedSweccis(pki, narrator.fas_track)
    radio = SimulatedRadioGateway(narrator.heard, voice)
    atak = SimulatedAtak(narrator.cot)
    cot_port = _free_udp_port()
    client_tls = {
        "ca_file": str(pki.ca_file),
        "cert_file": str(pki.client_cert),
        "key_file": str(pki.client_key),
    }
    for source in data["sources"]:
        if source["type"] == "cot":
            source["uri"] = f"udp://127.0.0.1:{cot_port}"
        elif source["type"] == "nffi":
            source["tls"].update(
                cert_file=str(pki.server_cert),
                key_file=str(pki.server_key),
                client_ca_file=str(pki.ca_file),
            )
    for processor in data["processors"]:
        if processor["type"] == "fusion":
            # Played ``speed`` times faster, everything moves that much faster on the wire.
            processor.setdefault("options", {})["speed_scale"] = speed
    for sink in data["sinks"]:
        options = sink["options"]
        if sink["type"] == "jsonl":
            options["path"] = str(archive)
        elif sink["type"] == "map":
            options["archive"] = str(archive)  # the map's time slider replays it
        elif sink["type"] == "gute2":
            options.update(client_tls, url=f"https://127.0.0.1:{battery.port}/gute2/handoffs")
        elif sink["type"] == "slb":
            options.update(client_tls, base_url=f"https://127.0.0.1:{slb.port}/slb/api")
        elif sink["type"] == "sweccis":
            options.update(client_tls, uri=f"tls://127.0.0.1:{sweccis.port}")
        elif sink["type"] == "ra180":
            options["udp"] = {"host": "127.0.0.1", "port": radio.port}
            options["bytes_per_minute"] = round(options["bytes_per_minute"] * max(speed, 1.0))
            if voice is None:
                options["voice"] = None
            else:
                options["voice"]["directory"] = str(voice)
        elif sink["type"] == "cot":
            options["destinations"] = [f"udp://127.0.0.1:{atak.port}"]
    return Demo(
        config=Config.model_validate(data),
        scenario=scenario,
        pki=pki,
        narrator=narrator,
        story=story,
        battery=battery,
        slb=slb,
        sweccis=sweccis,
        radio=radio,
        atak=atak,
        cot_port=cot_port,
        link_port=link_port,
        speed=speed,
        log_file=log_file,
        log_stream=log_stream,
        archive=archive,
    )
