"""The Ra 180 sink on real transports: UDP on loopback, a pseudo-terminal pair, espeak-ng."""

from __future__ import annotations

import array
import math
import os
import shutil
import socket
import subprocess
import sys
import wave
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import anyio
import pytest
from pydantic import ValidationError
from tools import need

from gateway.contract import check_sink
from gateway.errors import PermanentSinkError
from gateway.events import Position, Track
from sinks.ra180.cdm import compose, parse_cdm
from sinks.ra180.sink import Ra180Sink, Ra180SinkConfig
from sinks.ra180.voice import Voice, VoiceSettings, prune

pytestmark = pytest.mark.anyio

T0 = datetime(2026, 11, 25, 19, 58, tzinfo=UTC)
ESPEAK = shutil.which("espeak-ng")


def need_espeak() -> None:
    """Skip without espeak-ng, unless CI installed it (``.ci/run`` sets FG_REQUIRED_TOOLS)."""
    need("espeak-ng")


def track(n: int = 1, *, lat: float = 65.8235, status: str = "created") -> Track:
    return Track(
        event_id=f"e-{n}-{lat}",
        track_id=f"T-{n}",
        time=T0,
        status=status,  # type: ignore[arg-type]
        object_class="loitering_munition",
        confidence=0.95,
        position=Position(lat_deg=lat, lon_deg=21.6955),
        cep50_m=5.0,
        cep90_m=9.0,
        speed_mps=30.0,
        course_deg=270.0,
        first_seen=T0,
        last_seen=T0,
        hostility="hostile",
    )


def expected_text(t: Track, number: int = 1) -> str:
    return compose(t, message_type="MAL", number=number).text()


@asynccontextmanager
async def lifetime(sink: Ra180Sink) -> AsyncIterator[Ra180Sink]:
    """The sink opened and its lifetime running, as its runner does it."""
    async with anyio.create_task_group() as tg:
        await sink.open()
        await tg.start(sink.run)
        try:
            yield sink
        finally:
            tg.cancel_scope.cancel()
            await sink.aclose()


async def wait_for(predicate: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
    """Until ``predicate`` holds: a state the sink's own tasks change (no event to wait on)."""
    deadline = anyio.current_time() + timeout_s
    while not predicate():
        if anyio.current_time() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        await anyio.sleep(0.01)


async def read_line(fd: int) -> bytes:
    """Bytes from a pty master up to and including CR LF."""
    data = b""
    with anyio.fail_after(10):
        while not data.endswith(b"\r\n"):
            await anyio.wait_readable(fd)
            try:
                data += os.read(fd, 256)
            except BlockingIOError:
                continue
    return data


class TestConfig:
    """Options are checked at load, naming what is wrong."""

    def test_exactly_one_transport(self) -> None:
        with pytest.raises(ValidationError, match="exactly one of udp or serial"):
            Ra180SinkConfig.model_validate({})
        with pytest.raises(ValidationError, match="exactly one of udp or serial"):
            Ra180SinkConfig.model_validate(
                {"udp": {"host": "127.0.0.1", "port": 9}, "serial": {"device": "/dev/null"}}
            )

    def test_budget_and_text_options(self) -> None:
        udp = {"host": "127.0.0.1", "port": 9}
        with pytest.raises(ValidationError, match="more than burst_bytes"):
            Ra180SinkConfig.model_validate({"udp": udp, "bytes_per_minute": 250})
        with pytest.raises(ValidationError, match="originator"):
            Ra180SinkConfig.model_validate({"udp": udp, "originator": "two words"})
        with pytest.raises(ValidationError, match="not a serial line speed"):
            Ra180SinkConfig.model_validate({"serial": {"device": "/dev/x", "baud": 12345}})
        config = Ra180SinkConfig.model_validate(
            {"udp": udp, "originator": "Jägare1", "abbreviations": {"tank": "Strv-122"}}
        )
        assert config.originator == "JAGARE1"
        assert config.abbreviations == {"tank": "STRV-122"}

    def test_check_config_warns_of_a_missing_device_and_synthesiser(self, tmp_path: Path) -> None:
        config = tmp_path / "node.yaml"
        config.write_text(
            "airframes:\n"
            "  - {id: A, sysid: 1, links: [{uri: 'udp://127.0.0.1:9', security: unsecured}]}\n"
            "sinks:\n"
            "  - name: radio\n"
            "    type: ra180\n"
            "    options:\n"
            f"      serial: {{device: '{tmp_path / 'ttyNONE'}'}}\n"
            f"      voice: {{directory: '{tmp_path}', program: no-such-espeak}}\n"
            "      abbreviations: {tnak: T-72, tank: STRV, class_9: ROBOT}\n"
            "routes: [{sinks: [radio], kinds: [track]}]\n"
        )
        done = subprocess.run(
            [sys.executable, "-m", "gateway", "check-config", str(config)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        warnings = [line for line in done.stderr.splitlines() if line.endswith("(warning)")]
        assert len(warnings) == 3
        assert all(
            line.startswith(f"{config}:6 sinks[0].options: sink 'radio': ") for line in warnings
        )
        assert "ttyNONE does not exist now; messages wait for it" in warnings[0]
        assert "abbreviations for 'tnak': no track has such a class" in warnings[1]  # a typo
        assert "install" in warnings[2]
        assert "espeak-ng" in warnings[2]


class TestUdp:
    """A radio gateway on UDP gets one CDM per datagram."""

    async def test_the_contract_holds(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
            peer.bind(("127.0.0.1", 0))
            port = peer.getsockname()[1]
            await anyio.to_thread.run_sync(
                lambda: check_sink(Ra180Sink, {"udp": {"host": "127.0.0.1", "port": port}})
            )

    async def test_a_hostile_track_reaches_the_radio_gateway(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
            peer.bind(("127.0.0.1", 0))
            peer.setblocking(False)
            options = {"udp": {"host": "127.0.0.1", "port": peer.getsockname()[1]}}
            sink = Ra180Sink("radio", Ra180SinkConfig.model_validate(options))
            async with lifetime(sink):
                await sink.send([track()])
                with anyio.fail_after(10):
                    await anyio.wait_readable(peer)
                datagram = peer.recv(1024)
                # Counted sent once no refusal came back (gateway.transports.udp_peer).
                await wait_for(lambda: sink.status()["sent"] == 1, "counted sent")
            assert datagram.decode("ascii") == expected_text(track())
            assert parse_cdm(datagram.decode()).type == "MAL"
            detail = sink.status()
            assert (detail["sent"], detail["sent_new"], detail["held"]) == (1, 1, 0)

    async def test_a_polar_track_is_refused_by_id_and_the_rest_taken(self) -> None:
        options = {"udp": {"host": "127.0.0.1", "port": 9}}
        sink = Ra180Sink("radio", Ra180SinkConfig.model_validate(options))
        polar = track(2, lat=85.0)
        with pytest.raises(PermanentSinkError) as caught:
            await sink.send([track(1), polar])
        assert caught.value.event_ids == {polar.event_id}
        assert sink.budget.held == 1


class TestSerial:
    """A radio data terminal on a serial port: exact bytes, and a missing port retried."""

    async def test_a_pty_pair_receives_the_exact_bytes(self) -> None:
        master, slave = os.openpty()
        os.set_blocking(master, False)
        try:
            options = {"serial": {"device": os.ttyname(slave), "baud": 9600}}
            sink = Ra180Sink("radio", Ra180SinkConfig.model_validate(options))
            async with lifetime(sink):
                await sink.send([track()])
                received = await read_line(master)
        finally:
            os.close(master)
            os.close(slave)
        assert received == expected_text(track()).encode("ascii") + b"\r\n"

    async def test_a_missing_port_is_retried_until_it_appears(self, tmp_path: Path) -> None:
        device = tmp_path / "ttyRADIO"
        options = {"serial": {"device": str(device)}, "retry_initial_s": 0.05, "retry_max_s": 0.2}
        sink = Ra180Sink("radio", Ra180SinkConfig.model_validate(options))
        master, slave = os.openpty()
        os.set_blocking(master, False)
        try:
            async with lifetime(sink):
                await sink.send([track()])
                await wait_for(lambda: sink.radio_state == "waiting for radio", "retrying")
                assert "No such file" in sink.radio_reason
                assert sink.status()["held"] == 1
                device.symlink_to(os.ttyname(slave))  # the terminal is plugged in
                received = await read_line(master)
                await wait_for(lambda: sink.radio_state == "sending", "sending")
        finally:
            os.close(master)
            os.close(slave)
        assert received == expected_text(track()).encode("ascii") + b"\r\n"
        assert sink.status()["held"] == 0


def wav_facts(path: Path) -> tuple[float, float]:
    """(seconds, RMS of the 16-bit samples relative to full scale)."""
    with wave.open(str(path)) as wav:
        assert wav.getsampwidth() == 2
        frames = wav.readframes(wav.getnframes())
        seconds = wav.getnframes() / wav.getframerate()
    samples = array.array("h", frames)
    rms = math.sqrt(sum(s * s for s in samples) / max(1, len(samples))) / 32768
    return seconds, rms


class TestVoice:
    """espeak-ng's Swedish voice renders a real CDM; a missing espeak-ng is reported, not fatal."""

    async def test_a_real_cdm_is_spoken_in_swedish_to_a_wav(self, tmp_path: Path) -> None:
        need_espeak()
        voice = Voice(VoiceSettings(tmp_path / "wav", voice="sv"), sink="radio")
        cdm = compose(track(), message_type="MAL", number=17)
        async with anyio.create_task_group() as tg:
            tg.start_soon(voice.run)
            voice.submit(cdm)
            await wait_for(lambda: voice.counts.rendered + voice.counts.failed > 0, "a WAV", 60)
            tg.cancel_scope.cancel()
        assert voice.counts.failed == 0, voice.reason
        (wav,) = (tmp_path / "wav").glob("*.wav")
        assert wav.name.endswith("-NR0017-MAL.wav")
        seconds, rms = wav_facts(wav)
        # Some 60 words read at 140 a minute: well over ten seconds of speech, not silence.
        assert 10 < seconds < 120
        assert rms > 0.01
        assert list((tmp_path / "wav").glob(".*.part")) == []

    async def test_missing_espeak_is_a_clear_state_not_a_crash(self, tmp_path: Path) -> None:
        settings = VoiceSettings(tmp_path / "wav", program="espeak-ng-not-installed-here")
        voice = Voice(settings, sink="radio")
        async with anyio.create_task_group() as tg:
            tg.start_soon(voice.run)
            voice.submit(compose(track(), message_type="MAL", number=1))
            await wait_for(lambda: voice.counts.unavailable == 1, "the announcement counted")
            tg.cancel_scope.cancel()
        assert voice.state == "unavailable"
        assert "install the Debian package espeak-ng" in voice.reason

    async def test_the_sink_keeps_sending_without_a_voice(self, tmp_path: Path) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
            peer.bind(("127.0.0.1", 0))
            peer.setblocking(False)
            options: dict[str, Any] = {
                "udp": {"host": "127.0.0.1", "port": peer.getsockname()[1]},
                "voice": {"directory": str(tmp_path / "wav"), "program": "no-such-espeak"},
            }
            sink = Ra180Sink("radio", Ra180SinkConfig.model_validate(options))
            async with lifetime(sink):
                await sink.send([track()])
                with anyio.fail_after(10):
                    await anyio.wait_readable(peer)
                assert peer.recv(1024).startswith(b"MAL FIENDE LUFT-MUN POS ")
                await wait_for(lambda: sink.status()["voice"]["unavailable"] == 1, "counted")
            assert sink.status()["voice"]["state"] == "unavailable"

    def test_the_directory_is_kept_to_its_caps_oldest_first(self, tmp_path: Path) -> None:
        names = [f"2026112{n}T203421920410Z-00000{n}-NR000{n}-MAL.wav" for n in range(6)]
        for name in names:
            (tmp_path / name).write_bytes(b"x" * 1000)
        (tmp_path / "0000-not-ours.wav").write_bytes(b"x" * 1000)
        assert prune(tmp_path, max_files=4, max_bytes=10_000) == 2
        assert prune(tmp_path, max_files=10, max_bytes=2_500) == 2
        assert sorted(p.name for p in tmp_path.glob("*.wav")) == ["0000-not-ours.wav", *names[4:]]


class TestBudgetOnTheWire:
    """Through the sink and a real socket: the burst goes out highest priority first."""

    async def test_a_burst_of_50_sends_the_bucket_then_holds_the_rest(self) -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
            peer.bind(("127.0.0.1", 0))
            peer.setblocking(False)
            options = {
                "udp": {"host": "127.0.0.1", "port": peer.getsockname()[1]},
                "report": ["hostile", "suspect"],
                "bytes_per_minute": 300,  # the bucket (260 bytes) at once, then 40 a minute
            }
            sink = Ra180Sink("radio", Ra180SinkConfig.model_validate(options))
            suspect = [track(n).model_copy(update={"hostility": "suspect"}) for n in range(1, 11)]
            hostile = [track(n) for n in range(11, 51)]
            async with lifetime(sink):
                await sink.send(suspect + hostile)  # the suspect ones offered first
                # 91 bytes a message: two fit the bucket, the third waits 2 minutes.
                await wait_for(lambda: sink.status()["sent"] == 2, "the bucket spent")
                with anyio.move_on_after(0.3):  # nothing more may come for a while
                    await wait_for(lambda: sink.status()["sent"] > 2, "more")
                received = []
                while True:
                    try:
                        received.append(peer.recv(1024).decode("ascii"))
                    except BlockingIOError:
                        break
            detail = sink.status()
        assert len(received) == 2
        assert sum(map(len, received)) <= 260
        assert [parse_cdm(r).hostility for r in received] == ["FIENDE"] * 2
        assert [parse_cdm(r).number for r in received] == [11, 12]  # numbered as taken
        assert (detail["held"], detail["held_back"], detail["sent"]) == (48, 1, 2)
