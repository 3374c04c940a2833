"""The map's web application (Starlette): the page, its files, the picture and its stream.

Routes (docs/map.md §3):

- ``GET /``: the page; ``GET /static/...``: its script, style and the vendored libraries;
- ``GET /api/picture``: the whole picture as JSON (``seq`` says which change it includes);
  ``?at=<ISO 8601 time>``: the picture as it was then, from the archive (``archive``);
- ``GET /api/info``: the page's settings (title, whether there is an archive, the tiles);
- ``GET /api/archive``: the archive's span (its first event's time, and now);
- ``GET /tiles/{z}/{x}/{y}``: a tile of the local base map (``tiles``);
- ``GET /api/stream``: Server-Sent Events, a ``snapshot`` then one ``change`` per change;
  ``?layers=track,detection`` limits both to those layers;
- ``GET /api/mgrs?lat=..&lon=..``: the MGRS reference of a point (the page's cursor readout).

``Guard`` wraps it all: the connection cap (HTTP 503 beyond ``max_connections`` requests and
streams at once), the token (HTTP 401 without it) and the headers that keep a browser from
running anything but the page's own files (``Content-Security-Policy``).
"""

from __future__ import annotations

import hmac
import math
from collections.abc import AsyncIterator, Awaitable, Callable, MutableMapping
from datetime import UTC, datetime, timedelta
from http.cookies import SimpleCookie
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

import anyio
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import Request
from starlette.responses import (
    FileResponse,
    JSONResponse,
    RedirectResponse,
    Response,
    StreamingResponse,
)
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from gateway.domain.geodesy import to_mgrs
from sinks.map.archive import ArchiveBudget, Replay, archive_start, replay
from sinks.map.hub import CLOSED, Hub, sse
from sinks.map.picture import LAYERS, Picture
from sinks.map.tiles import TileSet

__all__ = ["STATIC", "TOKEN_COOKIE", "MapState", "build_app"]

STATIC = Path(__file__).with_name("static")
#: A stream's write gathers what is queued up to about this size.
_CHUNK_BYTES = 64 * 1024
_MAX_AT_CHARS = 40
#: A tile address's numbers: zoom at most 24, so x and y below 2**24 (8 digits).
_MAX_TILE_DIGITS = 9
TOKEN_COOKIE = "fg_map_token"  # noqa: S105 - the cookie's name, not a secret

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

_CSP = (
    "default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; connect-src 'self'; base-uri 'none'; form-action 'none'; "
    "frame-ancestors 'none'"
)
_HEADERS = [
    (b"content-security-policy", _CSP.encode()),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
    (b"x-frame-options", b"DENY"),
    (b"cache-control", b"no-store"),
]


class MapState:
    """What the application reads: the picture, the hub, the archive, tiles and settings."""

    def __init__(
        self,
        picture: Picture,
        hub: Hub,
        *,
        title: str,
        keepalive_s: float,
        archive: Path | None = None,
        budget: ArchiveBudget | None = None,
        tiles: TileSet | None = None,
    ) -> None:
        self.picture = picture
        self.hub = hub
        self.title = title
        self.keepalive_s = keepalive_s
        self.archive = archive
        self.budget = budget or ArchiveBudget()
        self.tiles = tiles
        self.refused_busy = 0
        self.refused_token = 0
        self.replays = 0
        self.replaying = False


def _at(text: str) -> datetime | str:
    """The time the ``at`` parameter names, or why it names none."""
    if len(text) > _MAX_AT_CHARS:
        return f"at: longer than {_MAX_AT_CHARS} characters"
    try:
        at = datetime.fromisoformat(text.strip())
    except ValueError:
        return "at: not an ISO 8601 time (e.g. 2026-11-27T06:30:00Z)"
    if at.tzinfo is None:
        return "at: give the time zone (Z for UTC)"
    now = datetime.now(UTC)
    if at > now + timedelta(minutes=1):
        return "at: in the future"
    if at.year < 2000:
        return "at: before 2000"
    return at.astimezone(UTC)


def _tile_address(params: dict[str, Any]) -> tuple[int, int, int] | None:
    """The three integers of ``/tiles/{z}/{x}/{y}``; None unless each is a few ASCII digits.

    Parsed here rather than by Starlette's ``int`` convertor, which turns an address of
    thousands of digits into a 500 (Python's limit on converting long digit strings).
    """
    numbers = []
    for key in ("z", "x", "y"):
        text = params.get(key)
        if not isinstance(text, str) or not text.isascii() or not text.isdigit():
            return None
        if len(text) > _MAX_TILE_DIGITS:
            return None
        numbers.append(int(text))
    return numbers[0], numbers[1], numbers[2]


def _layers(request: Request) -> frozenset[str] | Response:
    text = request.query_params.get("layers")
    if text is None:
        return frozenset(LAYERS)
    wanted = frozenset(part.strip() for part in text.split(",") if part.strip())
    unknown = sorted(wanted - set(LAYERS))
    if unknown or not wanted:
        return JSONResponse({"error": f"layers: give some of {', '.join(LAYERS)}"}, status_code=400)
    return wanted


def _snapshot(state: MapState, layers: frozenset[str]) -> dict[str, Any]:
    full = state.picture.snapshot()
    return {
        "seq": state.hub.seq,
        "title": state.title,
        "layers": {layer: full[layer] for layer in LAYERS if layer in layers},
    }


def build_app(
    state: MapState, *, allowed_hosts: list[str], token: str | None, max_connections: int
) -> ASGIApp:
    """The application, wrapped in its ``Guard``."""

    async def page(request: Request) -> Response:
        if token is not None and "token" in request.query_params:
            # The token came in the address (a bookmark): keep it in a cookie, drop it from
            # the address bar and the history.
            response = RedirectResponse("/", status_code=303)
            response.set_cookie(
                TOKEN_COOKIE,
                request.query_params["token"],
                httponly=True,
                samesite="strict",
                secure=request.url.scheme == "https",
            )
            return response
        return FileResponse(STATIC / "index.html", media_type="text/html")

    async def picture(request: Request) -> Response:
        layers = _layers(request)
        if isinstance(layers, Response):
            return layers
        if "at" in request.query_params:
            return await past(request.query_params["at"], layers)
        return JSONResponse(_snapshot(state, layers))

    async def past(text: str, layers: frozenset[str]) -> Response:
        if state.archive is None:
            return JSONResponse(
                {"error": "at: no archive (set the map sink's archive option)"}, status_code=404
            )
        at = _at(text)
        if isinstance(at, str):
            return JSONResponse({"error": at}, status_code=400)
        if state.replaying:
            return JSONResponse(
                {"error": "busy: one archive replay at a time"},
                status_code=503,
                headers={"retry-after": "1"},
            )
        archive = state.archive

        def job() -> Replay:
            try:
                return replay(archive, at, state.picture.limits, state.budget)
            finally:
                state.replaying = False  # when the thread is done, even if abandoned

        state.replaying = True
        # Abandoned on cancel (a drain, a client gone): the thread ends within its budget.
        done = await anyio.to_thread.run_sync(job, abandon_on_cancel=True)
        state.replays += 1
        full = done.picture.snapshot()
        return JSONResponse(
            {
                "seq": None,
                "title": state.title,
                "at": at.isoformat().replace("+00:00", "Z"),
                "replay": done.summary(),
                "layers": {layer: full[layer] for layer in LAYERS if layer in layers},
            }
        )

    async def info(request: Request) -> Response:
        return JSONResponse(
            {
                "title": state.title,
                "archive": state.archive is not None,
                "tiles": None if state.tiles is None else state.tiles.describe(),
            }
        )

    async def archive(request: Request) -> Response:
        if state.archive is None:
            return JSONResponse({"error": "no archive"}, status_code=404)
        start = await anyio.to_thread.run_sync(archive_start, state.archive, state.budget)
        return JSONResponse(
            {
                "start": None if start is None else start.isoformat().replace("+00:00", "Z"),
                "now": datetime.now(UTC).isoformat().replace("+00:00", "Z"),
            }
        )

    async def tile(request: Request) -> Response:
        tiles = state.tiles
        address = _tile_address(request.path_params)
        if tiles is None or address is None or not tiles.valid(*address):
            return Response(status_code=404)
        z, x, y = address
        found = await anyio.to_thread.run_sync(tiles.tile, z, x, y)
        if found is None:
            return Response(status_code=404)
        return Response(found[0], media_type=found[1])

    async def stream(request: Request) -> Response:
        layers = _layers(request)
        if isinstance(layers, Response):
            return layers
        sub = state.hub.subscribe(layers)
        first = sse("snapshot", _snapshot(state, layers), state.hub.seq)

        async def messages() -> AsyncIterator[bytes]:
            try:
                yield b"retry: 2000\n\n" + first
                while True:
                    message = b": keepalive\n\n"
                    with anyio.move_on_after(state.keepalive_s):
                        message = await sub.queue.get()
                    # What else is queued goes in the same write: fewer, larger writes.
                    chunk = [message]
                    size = len(message)
                    while message != CLOSED and size < _CHUNK_BYTES and not sub.queue.empty():
                        message = sub.queue.get_nowait()
                        chunk.append(message)
                        size += len(message)
                    if message == CLOSED:
                        if sub.overflowed:
                            chunk.append(sse("overflow", {"reason": "client too slow: reconnect"}))
                        yield b"".join(chunk)
                        return
                    yield b"".join(chunk)
            finally:
                state.hub.unsubscribe(sub)

        return StreamingResponse(
            messages(),
            media_type="text/event-stream",
            headers={"x-accel-buffering": "no"},
        )

    async def mgrs(request: Request) -> Response:
        try:
            lat = float(request.query_params["lat"])
            lon = float(request.query_params["lon"])
        except (KeyError, ValueError):
            return JSONResponse({"error": "give lat and lon in degrees"}, status_code=400)
        if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180):
            return JSONResponse({"error": "lat or lon out of range"}, status_code=400)
        try:
            return JSONResponse({"mgrs": to_mgrs(lat, lon, 1, spaced=True)})
        except ValueError as exc:  # beyond MGRS's latitudes (UPS)
            return JSONResponse({"mgrs": None, "error": str(exc)[:200]})

    app = Starlette(
        routes=[
            Route("/", page),
            Route("/api/picture", picture),
            Route("/api/stream", stream),
            Route("/api/mgrs", mgrs),
            Route("/api/info", info),
            Route("/api/archive", archive),
            Route("/tiles/{z}/{x}/{y}", tile),
            Route("/favicon.ico", lambda request: Response(status_code=204)),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ],
        middleware=[Middleware(TrustedHostMiddleware, allowed_hosts=allowed_hosts)],
    )
    return Guard(app, state, token=token, max_connections=max_connections)


class Guard:
    """The connection cap, the token check and the security headers, around ``app``."""

    def __init__(
        self, app: ASGIApp, state: MapState, *, token: str | None, max_connections: int
    ) -> None:
        self.app = app
        self.state = state
        self.token = token
        self.max_connections = max_connections
        self.active = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)  # lifespan
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", []), *_HEADERS]
            await send(message)

        if self.active >= self.max_connections:
            self.state.refused_busy += 1
            await _plain(send_with_headers, 503, b"busy: too many connections\n")
            return
        if self.token is not None and not self._authorised(scope):
            self.state.refused_token += 1
            await _plain(send_with_headers, 401, b"a token is required\n")
            return
        self.active += 1
        try:
            await self.app(scope, receive, send_with_headers)
        finally:
            self.active -= 1

    def _authorised(self, scope: Scope) -> bool:
        if self.token is None:
            return True
        offered: list[str] = []
        for key, value in scope.get("headers", []):
            if key == b"authorization":
                scheme, _, credential = value.decode("latin-1").partition(" ")
                if scheme.lower() == "bearer":
                    offered.append(credential.strip())
            elif key == b"cookie":
                cookie: SimpleCookie = SimpleCookie()
                try:
                    cookie.load(value.decode("latin-1"))
                except Exception:  # noqa: BLE001, S112 - a malformed cookie header is no token
                    continue
                if TOKEN_COOKIE in cookie:
                    offered.append(cookie[TOKEN_COOKIE].value)
        query = scope.get("query_string", b"").decode("latin-1")
        offered += parse_qs(query).get("token", [])[:1]
        expected = self.token.encode()
        return any(hmac.compare_digest(o.encode("utf-8", "replace"), expected) for o in offered)


async def _plain(send: Send, status: int, body: bytes) -> None:
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"text/plain; charset=utf-8"),
                (b"content-length", str(len(body)).encode()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})
