"""The SQLite spool: what it holds, for whom, across reopening and kill -9."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from spool_v1 import write_v1

from gateway.errors import SpoolError
from gateway.events import Detection, Position, Sensor
from gateway.spool.store import MAX_SINKS, Spool

T0 = datetime(2026, 11, 23, 12, 0, tzinfo=UTC)


def detection(n: int) -> Detection:
    return Detection(
        event_id=f"det-{n}",
        airframe="F26E-001",
        time=T0,
        sensor=Sensor.EO,
        object_class="tank",
        confidence=0.9,
        position=Position(lat_deg=58.4, lon_deg=15.6),
        sigma_h_m=8.0,
    )


def ids(spool: Spool, sink: str) -> list[str]:
    return [row.event.event_id for row in spool.pending(sink, limit=10**6)]


class TestOwing:
    def test_one_body_for_many_sinks_gone_with_the_last_confirmation(self) -> None:
        spool = Spool()
        seqs = [spool.append(detection(n), ("slb", "cot")) for n in range(3)]
        assert all(isinstance(seq, int) for seq in seqs)
        assert ids(spool, "slb") == ids(spool, "cot") == ["det-0", "det-1", "det-2"]
        spool.confirm("slb", [seqs[0], seqs[1]])  # type: ignore[list-item]
        assert ids(spool, "slb") == ["det-2"]
        assert ids(spool, "cot") == ["det-0", "det-1", "det-2"]
        assert spool.pending_counts() == {"slb": 1, "cot": 3}
        spool.confirm("cot", seqs)  # type: ignore[arg-type]
        spool.confirm("slb", [seqs[2]])  # type: ignore[list-item]
        assert spool.pending_counts() == {}
        rows = spool._db.execute("SELECT count(*) FROM events").fetchone()
        assert rows == (0,)

    def test_pending_after_a_seq_pages_in_order(self) -> None:
        spool = Spool()
        for n in range(25):
            spool.append(detection(n), ("s",))
        first = spool.pending("s", limit=10)
        second = spool.pending("s", after=first[-1].seq, limit=10)
        assert [r.event.event_id for r in first + second] == [f"det-{n}" for n in range(20)]

    def test_a_batch_commits_together_or_not_at_all(self, tmp_path: Path) -> None:
        spool = Spool(tmp_path / "spool.db")

        def failing_datagram() -> None:
            with spool.batch():
                spool.append(detection(1), ("s",))
                spool.remember("det-1")
                raise RuntimeError("the datagram handler failed")

        with pytest.raises(RuntimeError):
            failing_datagram()
        assert ids(spool, "s") == []
        assert not spool.seen("det-1")
        with spool.batch():
            spool.append(detection(2), ("s",))
            spool.remember("det-2")
        spool.close()
        again = Spool(tmp_path / "spool.db")
        assert ids(again, "s") == ["det-2"]
        assert again.seen("det-2")
        assert again.pending_counts() == {"s": 1}
        again.close()

    def test_sequence_numbers_grow_even_when_the_newest_event_is_gone(self) -> None:
        spool = Spool()
        first = spool.append(detection(1), ("s",))
        spool.confirm("s", [first])  # type: ignore[list-item]
        second = spool.append(detection(2), ("s",))
        assert first is not None
        assert second is not None
        assert second > first

    def test_reopening_continues_after_the_highest_held_seq(self, tmp_path: Path) -> None:
        spool = Spool(tmp_path / "spool.db")
        seqs = [spool.append(detection(n), ("s",)) for n in range(3)]
        spool.close()
        again = Spool(tmp_path / "spool.db")
        later = again.append(detection(3), ("s",))
        again.close()
        assert later is not None
        assert later > max(s for s in seqs if s is not None)


class TestDeadLetters:
    def test_dead_letters_keep_the_event_and_requeue_puts_it_last(self) -> None:
        spool = Spool()
        seqs = [spool.append(detection(n), ("slb",)) for n in range(3)]
        spool.dead_letter("slb", [seqs[0]], "422 unknown class")  # type: ignore[list-item]
        assert ids(spool, "slb") == ["det-1", "det-2"]
        (letter,) = spool.dead_letters()
        assert (letter.sink, letter.event_id, letter.reason) == (
            "slb",
            "det-0",
            "422 unknown class",
        )
        body = spool.dead_letter_body(letter.id)
        assert body is not None
        assert b'"det-0"' in body
        assert spool.requeue([letter.id]) == 1
        assert ids(spool, "slb") == ["det-1", "det-2", "det-0"]
        assert spool.dead_letters() == []
        assert spool.dead_letter_count() == 0

    def test_a_requeue_from_the_command_line_is_moved_by_the_owning_gateway(
        self, tmp_path: Path
    ) -> None:
        owner = Spool(tmp_path / "spool.db")
        seq = owner.append(detection(1), ("slb",))
        owner.dead_letter("slb", [seq], "403")  # type: ignore[list-item]
        beside = Spool(tmp_path / "spool.db", exclusive=False)
        (letter,) = beside.dead_letters()
        assert beside.requeue([letter.id, 999]) == 1
        assert ids(beside, "slb") == []  # only marked: the owner numbers events
        beside.close()
        assert owner.take_requeued() == 1
        assert ids(owner, "slb") == ["det-1"]
        assert owner.dead_letter_count() == 0
        owner.close()

    def test_the_oldest_dead_letters_make_room(self) -> None:
        spool = Spool(dead_letters_max=5)
        for n in range(8):
            seq = spool.append(detection(n), ("s",))
            spool.dead_letter("s", [seq], "no")  # type: ignore[list-item]
        assert [d.event_id for d in spool.dead_letters()] == [f"det-{n}" for n in (7, 6, 5, 4, 3)]
        assert spool.dead_letter_count() == 5

    def test_an_unreadable_row_is_dead_lettered_not_fatal(self) -> None:
        spool = Spool()
        spool.append(detection(1), ("s",))
        spool.append(detection(2), ("s",))
        spool._db.execute("UPDATE events SET body=? WHERE event_id='det-1'", (b"{not json",))
        assert ids(spool, "s") == ["det-2"]
        (letter,) = spool.dead_letters()
        assert letter.event_id == "det-1"
        assert "unreadable" in letter.reason


class TestLimits:
    def test_a_full_spool_refuses_and_takes_again_once_emptied(self) -> None:
        spool = Spool(max_bytes=256 * 1024)
        seqs = []
        for n in range(20_000):
            seq = spool.append(detection(n), ("s",))
            if seq is None:
                break
            seqs.append(seq)
        assert spool.is_full
        assert spool.refused == 1
        assert spool.append(detection(-1), ("s",)) is None
        spool.confirm("s", seqs)
        spool._db.execute("VACUUM")
        for n in range(300):  # the size is measured again every few hundred tries
            if spool.append(detection(10**6 + n), ("s",)) is not None:
                break
        else:
            pytest.fail("the spool never took events again after being emptied")

    def test_detection_ids_are_forgotten_after_the_window(self) -> None:
        spool = Spool(dedup_window_s=0.05)
        spool.remember("det-1")
        assert spool.seen("det-1")
        time.sleep(0.06)
        assert not spool.seen("det-1")

    def test_one_spool_file_belongs_to_one_gateway(self, tmp_path: Path) -> None:
        first = Spool(tmp_path / "spool.db")
        with pytest.raises(SpoolError, match="in use by another running fischer-gateway"):
            Spool(tmp_path / "spool.db")
        beside = Spool(tmp_path / "spool.db", exclusive=False)  # the spool command
        beside.close()
        first.close()
        Spool(tmp_path / "spool.db").close()  # released with the first

    def test_an_unopenable_path_is_a_spool_error_naming_it(self, tmp_path: Path) -> None:
        with pytest.raises(SpoolError, match="no-such-dir"):
            Spool(tmp_path / "no-such-dir" / "spool.db")


_WRITER = textwrap.dedent(
    """
    import sys
    from datetime import UTC, datetime
    from pathlib import Path
    from gateway.events import Detection, Position, Sensor
    from gateway.spool.store import Spool

    spool = Spool(Path(sys.argv[1]), sync=sys.argv[2])
    t = datetime(2026, 11, 23, tzinfo=UTC)
    n = 0
    while True:
        with spool.batch():
            for _ in range(5):
                spool.append(Detection(
                    event_id=f"det-{n}", airframe="F", time=t, sensor=Sensor.EO,
                    object_class="tank", confidence=0.5,
                    position=Position(lat_deg=1, lon_deg=1), sigma_h_m=1,
                ), ("slb", "sweccis"))
                spool.remember(f"det-{n}")
                n += 1
        print(n, flush=True)  # every detection below n is committed
    """
)


@pytest.mark.parametrize("sync", ["normal", "full"])
def test_kill_9_loses_nothing_that_was_committed(tmp_path: Path, sync: str) -> None:
    path = tmp_path / "spool.db"
    writer = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(path), sync],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert writer.stdout is not None
    committed = 0
    deadline = time.monotonic() + 30
    while committed < 500 and time.monotonic() < deadline:
        committed = int(writer.stdout.readline())
    writer.send_signal(signal.SIGKILL)
    writer.wait()
    writer.stdout.close()
    assert committed >= 500
    spool = Spool(path)
    for sink in ("slb", "sweccis"):
        held = ids(spool, sink)
        assert held[:committed] == [f"det-{n}" for n in range(committed)]
        assert len(held) % 5 == 0  # whole batches only
    assert spool.seen(f"det-{committed - 1}")
    spool.close()


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["append", "confirm", "dead"]),
            st.frozensets(st.sampled_from(["a", "b", "c"]), min_size=1),
            st.integers(min_value=0, max_value=30),
        ),
        max_size=60,
    )
)
def test_what_is_owed_matches_a_model(ops: list[tuple[str, frozenset[str], int]]) -> None:
    spool = Spool()
    model: dict[str, list[int]] = {"a": [], "b": [], "c": []}
    for n, (op, sinks, pick) in enumerate(ops):
        if op == "append":
            seq = spool.append(detection(n), tuple(sorted(sinks)))
            assert seq is not None
            for sink in sinks:
                model[sink].append(seq)
            continue
        for sink in sinks:
            if model[sink]:
                seq = model[sink].pop(pick % len(model[sink]))
                if op == "confirm":
                    spool.confirm(sink, [seq])
                else:
                    spool.dead_letter(sink, [seq], "model")
    for sink, seqs in model.items():
        assert [row.seq for row in spool.pending(sink, limit=10**6)] == sorted(seqs)
        assert spool.pending_count(sink) == len(seqs)
    live = {seq for seqs in model.values() for seq in seqs}
    rows = {r[0] for r in spool._db.execute("SELECT seq FROM events").fetchall()}
    assert rows == live  # no event body outlives the last sink owed it


class TestSchema1:
    """A spool file of schema 1 (a ``pending`` row per sink and event) is migrated at start."""

    def v1_file(self, tmp_path: Path) -> Path:
        path = tmp_path / "spool.db"
        events = [detection(n) for n in range(10)]
        # As schema 1 left it after: 10 events for (a, b), a confirmed 0-3, b confirmed 0-1
        # and refused 2 (a dead letter), det-0 taken in.
        write_v1(
            path,
            events,
            {"a": range(4, 10), "b": range(3, 10)},
            dead=[("b", events[2], "refused")],
            seen=["det-0"],
        )
        return path

    def test_every_owed_event_is_kept_in_order_for_its_sinks(self, tmp_path: Path) -> None:
        path = self.v1_file(tmp_path)
        spool = Spool(path)
        assert spool._db.execute("SELECT value FROM meta WHERE key='schema'").fetchone() == ("2",)
        tables = {r[0] for r in spool._db.execute("SELECT name FROM sqlite_master")}
        assert "pending" not in tables
        assert spool.pending_counts() == {"a": 6, "b": 7}
        assert ids(spool, "a") == [f"det-{n}" for n in range(4, 10)]
        assert ids(spool, "b") == [f"det-{n}" for n in range(3, 10)]
        assert [(d.sink, d.event_id) for d in spool.dead_letters()] == [("b", "det-2")]
        assert spool.seen("det-0")
        seq = spool.append(detection(10), ("a", "b", "c"))
        assert seq == 11  # numbering goes on after the migrated events
        spool.confirm("a", [row.seq for row in spool.pending("a")])
        spool.confirm("b", [row.seq for row in spool.pending("b")])
        spool.confirm("c", [11])
        assert spool.pending_counts() == {}
        assert spool._db.execute("SELECT count(*) FROM events").fetchone() == (0,)
        spool.close()
        again = Spool(path)  # nothing owed after the restart: nothing is sent twice
        assert again.pending_counts() == {}
        assert again.dead_letter_count() == 1
        again.close()

    def test_a_migration_cut_short_leaves_schema_1_and_runs_again(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        path = self.v1_file(tmp_path)
        connect = Spool._connect

        def failing(self: Spool, *args: Any, **kwargs: Any) -> sqlite3.Connection:
            db = connect(self, *args, **kwargs)

            def deny_drop(action: int, arg1: str | None, *_: object) -> int:
                # The migration's last step fails, as a kill -9 or a full disk would stop it.
                return sqlite3.SQLITE_DENY if action == sqlite3.SQLITE_DROP_TABLE else 0

            db.set_authorizer(deny_drop)
            return db

        monkeypatch.setattr(Spool, "_connect", failing)
        with pytest.raises(SpoolError, match="not authorized"):
            Spool(path)
        monkeypatch.undo()
        db = sqlite3.connect(path)
        assert db.execute("SELECT value FROM meta WHERE key='schema'").fetchone() == ("1",)
        assert db.execute("SELECT count(*) FROM pending").fetchone() == (13,)
        db.close()
        spool = Spool(path)  # the next start migrates it
        assert spool.pending_counts() == {"a": 6, "b": 7}
        spool.close()

    def test_the_command_beside_it_asks_for_the_gateway_to_migrate_it(self, tmp_path: Path) -> None:
        path = self.v1_file(tmp_path)
        with pytest.raises(SpoolError, match="spool schema 1; start this version's gateway"):
            Spool(path, exclusive=False)
        spool = Spool(path)
        assert spool.pending_counts() == {"a": 6, "b": 7}
        spool.close()

    def test_another_schema_is_refused_naming_it(self, tmp_path: Path) -> None:
        path = tmp_path / "spool.db"
        Spool(path).close()
        db = sqlite3.connect(path)
        with db:
            db.execute("UPDATE meta SET value='7' WHERE key='schema'")
        db.close()
        with pytest.raises(SpoolError, match="spool schema 7, this gateway reads 2"):
            Spool(path)


class TestSinkBits:
    def test_a_sink_owed_nothing_gives_its_bit_to_a_new_one(self) -> None:
        spool = Spool()
        names = [f"s{n}" for n in range(MAX_SINKS)]
        seqs = [spool.append(detection(n), (name,)) for n, name in enumerate(names)]
        with pytest.raises(SpoolError, match=f"owed to {MAX_SINKS} sinks already"):
            spool.append(detection(100), ("new",))
        spool.confirm("s7", [seqs[7]])  # type: ignore[list-item]
        seq = spool.append(detection(101), ("new",))
        assert ids(spool, "new") == ["det-101"]
        assert ids(spool, "s8") == ["det-8"]
        assert "s7" not in spool._bits
        spool.confirm("new", [seq])  # type: ignore[list-item]
        assert spool.pending_counts() == {name: 1 for name in names if name != "s7"}
