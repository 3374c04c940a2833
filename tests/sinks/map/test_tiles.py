"""Local tiles for the map: an MBTiles file (real SQLite, read-only) or a z/x/y directory."""

from __future__ import annotations

import zlib
from pathlib import Path

import anyio
import httpx
import pytest
from pydantic import ValidationError
from test_map import serving
from tile_support import png, write_directory, write_mbtiles

from gateway.errors import TransientSinkError
from sinks.map import MapSink, MapSinkConfig
from sinks.map.tiles import TilesError, open_tiles


def colour(z: int, x: int, y: int) -> tuple[int, int, int]:
    return (z * 40, x * 20, y * 20)


def pixel(data: bytes) -> tuple[int, int, int]:
    """The first pixel of a one-colour PNG made by tile_support.png."""
    start = data.index(b"IDAT") + 4
    length = int.from_bytes(data[start - 8 : start - 4], "big")
    raw = zlib.decompress(data[start : start + length])
    return raw[1], raw[2], raw[3]


def test_mbtiles_rows_are_turned_round_and_the_address_is_checked(tmp_path: Path) -> None:
    path = write_mbtiles(tmp_path / "lm.mbtiles", range(3), colour, attribution="© LM")
    tiles = open_tiles(path, fmt="png", min_zoom=None, max_zoom=None, attribution="")
    assert (tiles.min_zoom, tiles.max_zoom, tiles.attribution) == (0, 2, "© LM")
    for z, x, y in ((0, 0, 0), (1, 0, 1), (2, 3, 0), (2, 1, 2)):
        found = tiles.tile(z, x, y)
        assert found is not None
        assert found[1] == "image/png"
        assert pixel(found[0]) == colour(z, x, y)
    for z, x, y in ((3, 0, 0), (2, 4, 0), (2, 0, 4), (-1, 0, 0), (1, -1, 0)):
        assert tiles.tile(z, x, y) is None


def test_a_directory_serves_only_images_named_by_three_integers(tmp_path: Path) -> None:
    root = write_directory(tmp_path / "xyz", {(5, 17, 9): (1, 2, 3), (6, 34, 18): (4, 5, 6)})
    (root / "5" / "17" / "10.png").write_text("<script>alert(1)</script>")
    tiles = open_tiles(root, fmt="png", min_zoom=None, max_zoom=None, attribution="")
    assert (tiles.min_zoom, tiles.max_zoom) == (5, 6)
    found = tiles.tile(5, 17, 9)
    assert found is not None
    assert pixel(found[0]) == (1, 2, 3)
    assert tiles.tile(5, 17, 10) is None  # not an image: not served
    assert tiles.tile(5, 17, 11) is None


def test_unusable_tile_sets_are_refused_naming_the_file(tmp_path: Path) -> None:
    vector = write_mbtiles(tmp_path / "v.mbtiles", range(1), colour, format="pbf")
    (tmp_path / "junk.mbtiles").write_bytes(b"not a database at all" * 10)
    (tmp_path / "empty").mkdir()
    for path, words in (
        (vector, "only raster tiles"),
        (tmp_path / "junk.mbtiles", "not an MBTiles file"),
        (tmp_path / "empty", "no zoom directories"),
        (tmp_path / "missing.mbtiles", "neither a directory"),
    ):
        with pytest.raises(TilesError, match=words) as caught:
            open_tiles(path, fmt="png", min_zoom=None, max_zoom=None, attribution="")
        assert str(path) in str(caught.value)
    options = {"port": 0, "tiles": {"path": str(tmp_path / "junk.mbtiles")}}
    sink = MapSink("map", MapSinkConfig.model_validate(options))
    with pytest.raises(TransientSinkError, match=r"junk\.mbtiles"):
        anyio.run(sink.open)
    anyio.run(sink.aclose)
    with pytest.raises(ValidationError, match="min_zoom is above max_zoom"):
        MapSinkConfig.model_validate({"tiles": {"path": "x", "min_zoom": 9, "max_zoom": 3}})
    with pytest.raises(ValidationError, match="neither a directory nor a file"):
        MapSinkConfig.model_validate(
            {"tiles": {"path": str(tmp_path / "nowhere")}}, context={"environment": True}
        )


def test_the_listener_serves_the_tiles_and_the_page_learns_of_them(tmp_path: Path) -> None:
    path = write_mbtiles(tmp_path / "lm.mbtiles", range(2), colour)

    async def main() -> None:
        options = {"path": path, "attribution": "Lantmäteriet <b>"}
        async with serving(tiles=options) as sink, httpx.AsyncClient(base_url=sink.url or "") as c:
            info = (await c.get("/api/info")).json()
            assert info["tiles"] == {
                "min_zoom": 0,
                "max_zoom": 1,
                "attribution": "Lantmäteriet <b>",
                "kind": "mbtiles",
            }
            answer = await c.get("/tiles/1/1/0")
            assert answer.status_code == 200
            assert answer.headers["content-type"] == "image/png"
            assert answer.content == png(colour(1, 1, 0))
            for bad in ("/tiles/2/0/0", "/tiles/1/2/0", "/tiles/1/0", "/tiles/a/0/0"):
                assert (await c.get(bad)).status_code == 404, bad
            # Hostile addresses: thousands of digits (past Python's int conversion limit),
            # signs, other digits than ASCII, a file name, a traversal. All 404, none a 500.
            hostile = (
                "/tiles/1/" + "9" * 5000 + "/0",
                "/tiles/" + "1" * 40 + "/0/0",
                "/tiles/1/+1/0",
                "/tiles/1/-0/0",
                "/tiles/1/\u0661/0",
                "/tiles/1/1/0.png",
                "/tiles/1/%2e%2e/0",
            )
            for bad in hostile:
                answer = await c.get(bad)
                assert answer.status_code == 404, (bad[:40], answer.status_code)
            assert sink.status()["tiles"] == "mbtiles"

    anyio.run(main)
