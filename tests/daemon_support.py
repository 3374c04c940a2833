"""The daemon as an operator runs it: ``fischer-gateway run`` in a child process, for tests.

``Daemon`` starts ``python -m gateway run --config FILE``, collects its JSON log lines in a
thread, and reads ``/metrics`` and ``/status`` over real HTTP. Frames are made with
pymavlink (plain and signed) and with the tunnel's ``Sealer`` holding only a day key, as an
airframe would. Everything is on loopback.
"""

from __future__ import annotations

import hashlib
import http.client
import json
import os
import random
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from prometheus_client.parser import text_string_to_metric_families
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.fleet.dialect import fischer_detection
from gateway.fleet.security.signing import mavlink_timestamp_now
from gateway.fleet.security.tunnel import DayKeys, Sealer, derive_day_key

MASTER = hashlib.sha256(b"attack-test-master").digest()
SIGNING_KEY = hashlib.sha256(b"attack-test-signing").digest()


def utc_now() -> datetime:
    return datetime.now(UTC)


#: Ports handed out below the kernel's ephemeral range (32768-60999 on Linux): a port the
#: kernel picked by ``bind(0)`` is given again to the next process that sends without binding
#: (any client on the machine), which can take it between this test choosing it and the daemon
#: binding it. The kernel never picks these on its own, so only a process that names them can.
_PORT_RANGE = (20_000, 32_000)
_handed_out: set[int] = set()
_rng = random.Random(os.getpid() ^ time.monotonic_ns())


def _free_port(kind: int) -> int:
    for _ in range(1_000):
        port = _rng.randrange(*_PORT_RANGE)
        if port in _handed_out:
            continue
        with socket.socket(socket.AF_INET, kind) as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
        _handed_out.add(port)
        return port
    raise RuntimeError(f"no free port in {_PORT_RANGE}")


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing holds now and no other test here was given."""
    return _free_port(socket.SOCK_DGRAM)


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that nothing holds now and no other test here was given."""
    return _free_port(socket.SOCK_STREAM)


def write_key(path: Path, key: bytes) -> Path:
    path.write_text(key.hex() + "\n")
    path.chmod(0o600)
    return path


def wait_until(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.02)


class Daemon:
    """One ``fischer-gateway run`` child process and what it logged."""

    def __init__(self, config: Path, *, nofile: int | None = None) -> None:
        def limit() -> None:  # pragma: no cover - runs in the child
            if nofile is not None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

        self.proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", "run", "--config", str(config)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            preexec_fn=limit,
        )
        self.lines: list[dict[str, Any]] = []
        self.raw: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        started = self.wait_event("gateway_started", 20.0)
        self.health_port = int(started["health_port"])

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            text = raw.decode("utf-8", "replace").rstrip("\n")
            self.raw.append(text)
            try:
                self.lines.append(json.loads(text.lstrip("<0123456789>")))
            except json.JSONDecodeError:
                self.lines.append({"event": "(not json)", "text": text})

    def wait_event(self, event: str, timeout_s: float) -> dict[str, Any]:
        found: list[dict[str, Any]] = []

        def seen() -> bool:
            if self.proc.poll() is not None and not found:
                tail = "\n".join(self.raw[-20:])
                raise AssertionError(f"daemon exited {self.proc.returncode}:\n{tail}")
            found[:] = [line for line in list(self.lines) if line.get("event") == event]
            return bool(found)

        wait_until(seen, timeout_s, f"log event {event}")
        return found[0]

    def events(self, event: str) -> list[dict[str, Any]]:
        return [line for line in list(self.lines) if line.get("event") == event]

    def get(self, path: str, timeout_s: float = 5.0) -> tuple[int, bytes]:
        conn = http.client.HTTPConnection("127.0.0.1", self.health_port, timeout=timeout_s)
        try:
            conn.request("GET", path)
            response = conn.getresponse()
            return response.status, response.read()
        finally:
            conn.close()

    def status(self) -> dict[str, Any]:
        code, body = self.get("/status")
        assert code == 200
        return json.loads(body)  # type: ignore[no-any-return]

    def metric(self, name: str, **labels: str) -> float:
        """The sum of the samples of ``name`` whose labels include ``labels``."""
        code, body = self.get("/metrics")
        assert code == 200
        total = 0.0
        for family in text_string_to_metric_families(body.decode()):
            for sample in family.samples:
                if sample.name == name and labels.items() <= sample.labels.items():
                    total += sample.value
        return total

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(timeout=5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return int(self.proc.returncode)

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)
        self._reader.join(timeout=5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


@contextmanager
def running(config: Path, *, nofile: int | None = None) -> Iterator[Daemon]:
    daemon = Daemon(config, nofile=nofile)
    try:
        yield daemon
    finally:
        daemon.stop()


class Airframe:
    """Frames as airframe ``sysid`` would send them: plain, signed, or sealed in the tunnel."""

    def __init__(self, sysid: int, *, signing_key: bytes | None = None) -> None:
        self.mav = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.link_id = 0
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = mavlink_timestamp_now(time.time())
        self.detections = 0

    def heartbeat(self) -> bytes:
        return bytes(self.mav.heartbeat_encode(1, 3, 0, 0, 4).pack(self.mav))

    def position(self, lat_deg: float = 59.3, lon_deg: float = 18.1) -> bytes:
        msg = self.mav.global_position_int_encode(
            1000, round(lat_deg * 1e7), round(lon_deg * 1e7), 120_000, 100_000, 0, 0, 0, 9000
        )
        return bytes(msg.pack(self.mav))

    def detection(self, subtype: str = "T-72") -> bytes:
        self.detections += 1
        msg = fischer_detection(
            time_usec=round(time.time() * 1e6),
            detection_id=self.detections,
            lat_e7=593_300_000,
            lon_e7=181_000_000,
            alt_msl_m=30.0,
            sigma_h_m=8.0,
            class_id=1,
            sensor=1,
            confidence_pct=91,
            subtype=subtype,
        )
        return bytes(msg.pack(self.mav))


def sealer(airframe_id: str) -> Sealer:
    """A sealer holding only today's and tomorrow's day keys, as an airframe does."""
    today = utc_now().date()
    keys = {
        (airframe_id, day): derive_day_key(MASTER, airframe_id, day)
        for day in (today, today.fromordinal(today.toordinal() + 1))
    }
    return Sealer(airframe_id, DayKeys(keys=keys), utc_now)


def three_airframe_node(
    tmp_path: Path, ports: dict[str, int], *, tun_extra: str = ""
) -> tuple[Path, Path]:
    """A node with a tunnel (TUN, sysid 1), a signed (SIG, 2) and an unsecured (OPEN, 3)
    airframe on the UDP ports ``ports["tun"|"sig"|"open"]``, and a jsonl archive.

    ``tun_extra`` adds YAML lines (indented four spaces) to TUN. Returns (config, archive).
    """
    archive = tmp_path / "archive.jsonl"
    master = write_key(tmp_path / "master.key", MASTER)
    signing = write_key(tmp_path / "signing.key", SIGNING_KEY)
    config = tmp_path / "node.yaml"
    config.write_text(
        f"""
gateway: {{shutdown_deadline_s: 2}}
health: {{port: 0}}
tunnel: {{master_key_file: '{master}'}}
airframes:
  - id: TUN
    sysid: 1
{tun_extra}    links: [{{uri: 'udp://127.0.0.1:{ports["tun"]}', security: tunnel, name: tun}}]
  - id: SIG
    sysid: 2
    signing: {{key_file: '{signing}'}}
    links: [{{uri: 'udp://127.0.0.1:{ports["sig"]}', security: signed, name: sig}}]
  - id: OPEN
    sysid: 3
    links: [{{uri: 'udp://127.0.0.1:{ports["open"]}', security: unsecured, name: open}}]
sinks:
  - {{name: archive, type: jsonl, options: {{path: '{archive}'}}}}
routes:
  - {{sinks: [archive]}}
"""
    )
    return config, archive


def archive_events(path: Path, *, torn: bool = False) -> list[dict[str, Any]]:
    """The events of a jsonl archive the daemon may be writing at this moment.

    A last line with no newline yet is being written and is left out. With ``torn``, lines
    that do not parse are left out too: a daemon killed mid-line leaves its partial line, which
    the jsonl sink ends with a newline when it opens the file again.
    """
    if not path.exists():
        return []
    text = path.read_text()
    if not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    events = []
    for line in text.splitlines():
        if not line.strip():
            continue
        try:
            events.append(json.loads(line))
        except json.JSONDecodeError:
            if not torn:
                raise
    return events
