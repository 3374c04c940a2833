"""The map's replay of the JSONL archive: the picture at an instant, bounded, hostile lines.

The archive is written here as the ``jsonl`` sink writes it (one ``model_dump_json`` line per
event; rotated files ``<stem>-YYYYmmddTHHMMSSZ<suffix>``). The endpoint is tested through the
real server (``serving`` from test_map).
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import anyio
import httpx
from test_map import serving

from gateway.contract import sample_events
from gateway.events import BlueForce, Event, EventKind, Position, Track
from sinks.map.archive import ArchiveBudget, archive_files, archive_start, replay
from sinks.map.picture import Limits, Picture

T0 = datetime(2026, 11, 27, 6, 0, tzinfo=UTC)


def track(track_id: str, second: float, lat: float, status: str = "updated") -> Track:
    when = T0 + timedelta(seconds=second)
    return Track(
        event_id=f"{track_id}-{second}",
        track_id=track_id,
        time=when,
        status=status,  # type: ignore[arg-type]
        object_class="loitering_munition",
        confidence=0.9,
        position=Position(lat_deg=lat, lon_deg=21.6),
        cep50_m=10.0,
        cep90_m=20.0,
        first_seen=T0,
        last_seen=when,
        hostility="hostile",
    )


def unit(uid: str, second: float, lat: float) -> BlueForce:
    return BlueForce(
        event_id=f"{uid}-{second}",
        uid=uid,
        time=T0 + timedelta(seconds=second),
        callsign=uid,
        position=Position(lat_deg=lat, lon_deg=21.0),
        source="cot",
    )


def write(path: Path, events: list[Event], *extra: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    # In arrival order, which is time order here, as a node writes them.
    events = sorted(events, key=lambda e: e.time)
    lines = b"".join(e.model_dump_json().encode() + b"\n" for e in events)
    path.write_bytes(lines + b"".join(extra))
    return path


def at(second: float) -> datetime:
    return T0 + timedelta(seconds=second)


def test_the_picture_at_an_instant_is_where_each_entity_was_then(tmp_path: Path) -> None:
    live = tmp_path / "archive.jsonl"
    # Opened at 05:59:50 and rotated; the live file holds what came after.
    write(
        tmp_path / "archive-20261127T055950Z.jsonl",
        [track("T1", s, 65.0 + s / 1000) for s in range(30)] + [unit("PLT-1", 5, 64.0)],
    )
    write(
        live,
        [track("T1", s, 65.0 + s / 1000) for s in range(30, 60)]
        + [track("T2", 40, 66.0), track("T2", 45, 66.0, "lost"), unit("PLT-1", 50, 64.5)],
    )
    limits = Limits(history_points=3)
    for second, lat, blue in ((20.5, 65.020, 64.0), (42, 65.042, 64.0), (59, 65.059, 64.5)):
        done = replay(live, at(second), limits, ArchiveBudget())
        snap = done.picture.snapshot()
        (t1,) = [e for e in snap["track"] if e["id"] == "T1"]
        assert t1["lat"] == lat
        assert t1["history"][-1] == [lat, 21.6]
        assert len(t1["history"]) == 3
        assert [e["lat"] for e in snap["blue"]] == [blue]
        assert done.truncated is None
        assert done.skipped == 0
    # T2 lived from 40 s until lost at 45 s.
    ids = {
        s: {
            e["id"]
            for e in replay(live, at(s), limits, ArchiveBudget()).picture.snapshot()["track"]
        }
        for s in (39, 42, 46)
    }
    assert ids == {39: {"T1"}, 42: {"T1", "T2"}, 46: {"T1"}}
    # Before the archive began: nothing.
    assert replay(live, at(-60), limits, ArchiveBudget()).picture.sizes()["track"] == 0


def test_what_had_expired_by_then_is_gone_and_old_files_are_not_opened(tmp_path: Path) -> None:
    live = tmp_path / "archive.jsonl"
    write(tmp_path / "archive-20261127T010000Z.jsonl", [unit("OLD", -14_000, 60.0)])
    write(tmp_path / "archive-20261127T055000Z.jsonl", [unit("PLT-1", 0, 64.0)])
    write(tmp_path / "archive-20261127T070000Z.jsonl", [unit("LATER", 3600, 61.0)])
    write(live, [unit("PLT-2", 3700, 62.0)])
    assert [p.name for _, p in archive_files(live)] == [
        "archive-20261127T010000Z.jsonl",
        "archive-20261127T055000Z.jsonl",
        "archive-20261127T070000Z.jsonl",
        "archive.jsonl",
    ]
    limits = Limits(expire_after_s=600)
    done = replay(live, at(300), limits, ArchiveBudget())
    assert [e["id"] for e in done.picture.snapshot()["blue"]] == ["PLT-1"]
    assert done.files == 1  # neither the file closed hours before nor those opened after
    assert replay(live, at(700), limits, ArchiveBudget()).picture.sizes()["blue"] == 0
    assert archive_start(live, ArchiveBudget()) == at(-14_000)
    assert archive_start(tmp_path / "none.jsonl", ArchiveBudget()) is None


def test_only_the_window_of_a_long_archive_is_read(tmp_path: Path) -> None:
    # One unit reporting every second for six hours, in one file.
    live = write(tmp_path / "archive.jsonl", [unit("U", s, 60 + s / 1e5) for s in range(21_600)])
    size = live.stat().st_size
    done = replay(live, at(10_000.5), Limits(expire_after_s=60), ArchiveBudget())
    assert [e["lat"] for e in done.picture.snapshot()["blue"]] == [60.1]
    assert done.truncated is None
    assert done.bytes_read < size / 10  # bisection found the window: not the whole file
    # A budget smaller than the window: its part nearest the instant is read.
    cut = replay(live, at(10_000.5), Limits(expire_after_s=600), ArchiveBudget(max_bytes=20_000))
    assert cut.truncated is not None
    assert [e["lat"] for e in cut.picture.snapshot()["blue"]] == [60.1]


def test_hostile_lines_are_skipped_and_counted(tmp_path: Path) -> None:
    live = write(
        tmp_path / "archive.jsonl",
        [track("T1", 1, 65.0)],
        b"not json\n",
        b"[1, 2]\n",
        b'{"kind": "track", "time": "yesterday"}\n',
        b'{"kind": "track", "time": "2026-11-27T06:00:02Z", "track_id": "X"}\n',
        b'{"kind": "track", "time": "2026-11-27T06:00:02"}\n',
        b'{"kind": "track", "time": "' + b"9" * 5000 + b'"}\n',
        b'{"pad": "' + b"x" * 3000 + b'", "kind": "track"}\n',
        track("T1", 3, 65.5).model_dump_json().encode() + b"\n",
        b'{"kind": "track", "time": "2026-11-27T06:00:04Z", "unfinished',
    )
    done = replay(live, at(10), Limits(), ArchiveBudget(max_line_bytes=2048))
    assert [e["lat"] for e in done.picture.snapshot()["track"]] == [65.5]
    assert done.skipped == 8
    assert done.events == 2


def test_a_replay_is_bounded_in_bytes_and_in_what_it_keeps(tmp_path: Path) -> None:
    # 20,000 tracks each reported once: only the picture's cap of them is kept.
    live = write(tmp_path / "archive.jsonl", [track(f"T{i}", i / 100, 65.0) for i in range(20_000)])
    done = replay(live, at(300), Limits(tracks=50), ArchiveBudget())
    assert done.picture.sizes()["track"] == 50
    assert done.events == 50  # only those were validated and applied
    assert {e["id"] for e in done.picture.snapshot()["track"]} == {
        f"T{i}" for i in range(19_950, 20_000)
    }
    # A window holding more than the budget: its newest part, nearest the instant, is read.
    small = replay(live, at(300), Limits(), ArchiveBudget(max_bytes=100_000))
    assert small.truncated is not None
    assert small.truncated.startswith("the window holds more than 100000 bytes")
    assert small.bytes_read <= 100_000 + 2048
    ids = {e["id"] for e in small.picture.snapshot()["track"]}
    assert "T19999" in ids
    assert "T0" not in ids
    slow = replay(
        live,
        at(300),
        Limits(),
        ArchiveBudget(max_seconds=0.001),
        clock=iter(range(0, 10**9, 5)).__next__,
    )
    assert slow.truncated is not None
    assert "s" in slow.truncated


def test_the_endpoint_answers_a_past_instant_and_refuses_without_an_archive(tmp_path: Path) -> None:
    live = write(tmp_path / "archive.jsonl", [track("T1", s, 65.0 + s / 100) for s in range(10)])

    async def main() -> None:
        async with (
            serving(archive=live) as sink,
            httpx.AsyncClient(base_url=sink.url or "") as client,
        ):
            answer = await client.get("/api/picture", params={"at": "2026-11-27T06:00:04.5Z"})
            assert answer.status_code == 200
            body = answer.json()
            assert body["at"] == "2026-11-27T06:00:04.500000Z"
            assert [e["lat"] for e in body["layers"]["track"]] == [65.04]
            assert body["replay"]["files"] == 1
            assert body["seq"] is None
            info = (await client.get("/api/info")).json()
            assert info == {"title": "Fischer gateway", "archive": True, "tiles": None}
            span = (await client.get("/api/archive")).json()
            assert span["start"] == "2026-11-27T06:00:00Z"
            sink._state.replaying = True  # another replay is running
            busy = await client.get("/api/picture", params={"at": "2026-11-27T06:00:04Z"})
            assert busy.status_code == 503
            assert "one archive replay" in busy.json()["error"]
        async with serving() as sink, httpx.AsyncClient(base_url=sink.url or "") as client:
            none = await client.get("/api/picture", params={"at": "2026-11-27T06:00:04Z"})
            assert none.status_code == 404
            assert "archive option" in none.json()["error"]
            assert (await client.get("/api/archive")).status_code == 404

    anyio.run(main)


def test_every_layer_replays_as_the_live_picture_drew_it(tmp_path: Path) -> None:
    """Airframes, links, detections, tracks, units, cues, orders and their status: the replay
    at an instant equals the live picture fed the same events up to it."""
    first = list(sample_events(frozenset(EventKind)))
    start = first[0].time
    cue = next(e for e in first if e.kind == EventKind.HANDOFF)
    revised = cue.model_copy(
        update={"revision": 1, "time": start + timedelta(seconds=10), "note": "revised"}
    )
    live = write(tmp_path / "archive.jsonl", [*first, revised])
    for seconds, events in ((5, first), (15, [*first, revised])):
        expected = Picture(Limits())
        for event in events:
            expected.apply(event)
        done = replay(live, start + timedelta(seconds=seconds), Limits(), ArchiveBudget())
        assert done.picture.snapshot() == expected.snapshot()
        assert done.skipped == 0
    (shown,) = done.picture.snapshot()["cue"]
    assert [r["revision"] for r in shown["revisions"]] == [0, 1]
    assert all(done.picture.sizes()[layer] == 1 for layer in ("airframe", "track", "order"))
