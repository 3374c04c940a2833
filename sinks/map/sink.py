"""The map sink: a live map page served by the node, and its change stream (docs/map.md).

The sink keeps the current picture (``sinks.map.picture``) from the events routed to it and
serves, on its own listener, a page that draws it (Leaflet, milsymbol, an offline base map)
and a Server-Sent Events stream of its changes, which is also how an integrator's program
subscribes without writing a sink. ``send`` only folds events into the picture and queues the
changes for the streams: it never waits on a browser.

The listener is bound in ``open`` and served by hypercorn in the sink's ``run`` lifetime,
inside the daemon's event loop; cancelling ``run`` (drain, reload, a reopen) ends every
stream, then the server. The picture outlives a reopen. Starlette and hypercorn come with the
``map`` extra (``pip install 'fischer-gateway[map]'``); without them the config names it.
"""

from __future__ import annotations

import asyncio
import importlib.util
import socket
import ssl
from collections.abc import Mapping, Sequence
from typing import Any

import anyio
import anyio.abc
import structlog

from gateway.errors import TransientSinkError
from gateway.events import Event, EventKind
from sinks.map.archive import ArchiveBudget
from sinks.map.config import MapSinkConfig, MapTls, is_loopback, read_token
from sinks.map.hub import Hub
from sinks.map.picture import Limits, Picture
from sinks.map.tiles import TilesError, TileSet, open_tiles

__all__ = ["EXTRA_MISSING", "MapSink"]

log = structlog.get_logger(__name__)

EXTRA_MISSING = (
    "the map sink needs Starlette and hypercorn, which are not installed: "
    "pip install 'fischer-gateway[map]'"
)
_EXPIRE_EVERY_S = 5.0
_STOP_S = 3.0


def _extra_installed() -> bool:
    return all(importlib.util.find_spec(name) is not None for name in ("starlette", "hypercorn"))


class MapSink:
    """Keeps the picture and serves the page and its change stream."""

    config_model = MapSinkConfig

    def __init__(self, name: str, config: MapSinkConfig) -> None:
        if not _extra_installed():
            raise ValueError(EXTRA_MISSING)
        self.name = name
        self.config = config
        self.log = log.bind(sink=name)
        self._token = None if config.token_file is None else read_token(config.token_file)
        self.picture = Picture(
            Limits(
                airframes=config.max_airframes,
                tracks=config.max_tracks,
                blue=config.max_blue,
                cues=config.max_cues,
                orders=config.max_orders,
                detections=config.max_detections,
                history_points=config.history_points,
                cue_revisions=config.cue_revisions,
                expire_after_s=config.expire_after_s,
            )
        )
        self.hub = Hub(queue_max=config.queue_max)
        self._socket: socket.socket | None = None
        self._state: Any = None
        self._tiles: TileSet | None = None
        self.url: str | None = None
        self._counts = {"applied": 0, "ignored": 0}

    @property
    def kinds(self) -> frozenset[EventKind]:
        """What the map draws (``kinds`` option)."""
        return self.config.kinds

    async def open(self) -> None:
        """Bind the listener; ``TransientSinkError`` if the address is taken or TLS unusable."""
        from sinks.map.server import listen

        if self.config.tls is not None:
            _check_tls(self.config.tls, self.name)
        self._tiles = self._open_tiles()
        host = self.config.host.strip("[]")  # an IPv6 literal may be written as in a URL
        try:
            self._socket = listen(host, self.config.port, self.config.stall_s)
        except OSError as exc:
            raise TransientSinkError(
                f"sink {self.name}: cannot listen on {self.config.host}:{self.config.port}: "
                f"{exc.strerror or exc}",
                sink=self.name,
            ) from exc
        port = self._socket.getsockname()[1]
        scheme = "https" if self.config.tls is not None else "http"
        shown = f"[{host}]" if ":" in host else host
        self.url = f"{scheme}://{shown}:{port}/"
        self.hub = Hub(queue_max=self.config.queue_max, seq=self.hub.seq)  # seq goes on
        self.log.info("map_listening", url=self.url, port=port, token=self._token is not None)

    async def run(self, *, task_status: anyio.abc.TaskStatus[None]) -> None:
        """Serve until cancelled; raise (to be reopened) if the server stops by itself."""
        from sinks.map.server import serve_app
        from sinks.map.web import MapState, build_app

        if self._socket is None:
            raise TransientSinkError(f"sink {self.name}: not open", sink=self.name)
        state = MapState(
            self.picture,
            self.hub,
            title=self.config.title,
            keepalive_s=self.config.keepalive_s,
            archive=self.config.archive,
            budget=ArchiveBudget(
                max_bytes=self.config.replay_max_mb * 1024 * 1024,
                max_seconds=self.config.replay_max_s,
            ),
            tiles=self._tiles,
        )
        self._state = state
        app = build_app(
            state,
            allowed_hosts=self._allowed_hosts(),
            token=self._token,
            max_connections=self.config.max_connections,
        )
        shutdown = asyncio.Event()
        server = asyncio.get_running_loop().create_task(
            serve_app(app, self._socket, self.config.tls, shutdown)
        )
        try:
            task_status.started()
            async with anyio.create_task_group() as tg:
                tg.start_soon(self._expire_forever)
                await asyncio.shield(server)
                tg.cancel_scope.cancel()
            raise TransientSinkError(f"sink {self.name}: the map server stopped", sink=self.name)
        finally:
            self.hub.close()  # every stream ends, so the server can close its connections
            shutdown.set()
            with anyio.CancelScope(shield=True), anyio.move_on_after(_STOP_S):
                await asyncio.wait({server})
            if not server.done():
                server.cancel()
            elif not server.cancelled() and server.exception() is not None:
                self.log.warning("map_server_failed", reason=repr(server.exception())[:300])

    async def _expire_forever(self) -> None:
        while True:
            await anyio.sleep(_EXPIRE_EVERY_S)
            self.hub.publish(self.picture.expire())

    async def send(self, batch: Sequence[Event]) -> None:
        """Fold each event into the picture and queue its changes for the streams."""
        for event in batch:
            changes = self.picture.apply(event)
            self._counts["applied" if changes else "ignored"] += 1
            self.hub.publish(changes)

    async def aclose(self) -> None:
        """Close the listener; safe when ``open`` never ran."""
        self.hub.close()
        sock, self._socket = self._socket, None
        if sock is not None:
            sock.close()

    def status(self) -> dict[str, Any]:
        """The URL, the picture's sizes and the streams, for ``/status``."""
        state = self._state
        return {
            "url": self.url,
            "entities": self.picture.sizes(),
            "streams": self.hub.subscribers,
            "seq": self.hub.seq,
            "evicted": self.picture.evicted,
            "expired": self.picture.expired,
            "refused_busy": 0 if state is None else state.refused_busy,
            "refused_token": 0 if state is None else state.refused_token,
            "replays": 0 if state is None else state.replays,
            "tiles": None if self._tiles is None else self._tiles.kind,
        }

    def counts(self) -> Mapping[str, int]:
        """Monotonic counts by outcome: events applied, ignored, entities evicted, streams cut."""
        return {
            **self._counts,
            "evicted": self.picture.evicted,
            "expired": self.picture.expired,
            "streams_cut": self.hub.cut_off,
        }

    def _open_tiles(self) -> TileSet | None:
        tiles = self.config.tiles
        if tiles is None:
            return None
        try:
            return open_tiles(
                tiles.path,
                fmt=tiles.format,
                min_zoom=tiles.min_zoom,
                max_zoom=tiles.max_zoom,
                attribution=tiles.attribution,
            )
        except (TilesError, OSError) as exc:
            raise TransientSinkError(f"sink {self.name}: {exc}", sink=self.name) from exc

    def _allowed_hosts(self) -> list[str]:
        host = self.config.host.strip("[]")
        names = [host, *self.config.allowed_hosts]
        if is_loopback(host):
            names += ["127.0.0.1", "localhost", "::1", "[::1]"]
        elif host in ("0.0.0.0", "::"):  # noqa: S104 - the names it is reached by are unknown
            return ["*"] if not self.config.allowed_hosts else names
        return sorted(set(names))


def _check_tls(tls: MapTls, sink: str) -> None:
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    try:
        context.load_cert_chain(str(tls.cert_file), str(tls.key_file))
        if tls.client_ca_file is not None:
            context.load_verify_locations(str(tls.client_ca_file))
    except (OSError, ssl.SSLError) as exc:
        raise TransientSinkError(f"sink {sink}: TLS files unusable: {exc}", sink=sink) from exc
