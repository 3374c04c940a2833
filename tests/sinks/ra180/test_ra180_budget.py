"""The Ra 180 byte budget: a burst fits the minute, highest priority first, held memory bounded."""

from __future__ import annotations

from datetime import UTC, datetime

from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.domain.geodesy import destination
from gateway.events import Position, Track
from sinks.ra180.budget import Budget, Outgoing, Priority
from sinks.ra180.cdm import Cdm, MessageType, compose

T0 = datetime(2026, 11, 25, 20, 0, tzinfo=UTC)
LAT, LON = 65.82, 21.69
BYTES_PER_MINUTE = 1200


def track(
    n: int, *, north_m: float = 0.0, hostility: str = "hostile", status: str = "created"
) -> Track:
    lat, lon = destination(LAT, LON + n * 0.01, 0.0, north_m)
    return Track(
        event_id=f"e-{n}-{north_m}-{status}",
        track_id=f"T-{n:03d}",
        time=T0,
        status=status,  # type: ignore[arg-type]
        object_class="loitering_munition",
        confidence=0.9,
        position=Position(lat_deg=lat, lon_deg=lon),
        cep50_m=5.0,
        cep90_m=9.0,
        first_seen=T0,
        last_seen=T0,
        hostility=hostility,  # type: ignore[arg-type]
    )


def encode(t: Track, message_type: MessageType, number: int) -> tuple[Cdm, bytes]:
    cdm = compose(t, message_type=message_type, number=number)
    return cdm, " ".join(cdm.fields()).encode() + b"\r\n"


def budget(**overrides: object) -> Budget:
    options: dict[str, object] = {
        "bytes_per_minute": BYTES_PER_MINUTE,
        "burst_bytes": 260,
        "min_move_m": 100.0,
        "max_tracks": 1000,
        "report": frozenset({"hostile", "suspect"}),
        "now": 0.0,
    }
    options.update(overrides)
    return Budget(encode, **options)  # type: ignore[arg-type]


def drain(b: Budget, now: float, until_s: float) -> list[tuple[float, Outgoing]]:
    """Send everything the budget lets out, stepping a fake clock; (time, message) each."""
    sent: list[tuple[float, Outgoing]] = []
    while now <= until_s:
        item = b.next_due(now)
        if item is not None:
            b.sent(item, now)
            sent.append((now, item))
            continue
        wait = b.wait_s(now)
        if wait is None:
            break
        now += wait
    return sent


class TestBurst:
    """Fifty tracks at once: within bytes_per_minute, in priority order, the rest held."""

    def test_a_burst_of_50_tracks_fits_the_budget_highest_priority_first(self) -> None:
        b = budget()
        for n in range(10):  # ten tracks the net already knows
            assert b.offer(track(n)) == "held"
        first = drain(b, 0.0, 600.0)
        assert [item.priority for _, item in first] == [Priority.NEW] * 10
        start = first[-1][0] + 120.0  # the bucket has refilled
        # The burst: ten of them moved 500 m (updates), 35 new hostile, 5 new suspect,
        # offered updates first so that order alone would be wrong.
        for n in range(10):
            assert b.offer(track(n, north_m=500.0, status="updated")) == "held"
        for n in range(10, 45):
            assert b.offer(track(n)) == "held"
        for n in range(45, 50):
            assert b.offer(track(n, hostility="suspect")) == "held"
        assert b.held == 50
        sent = drain(b, start, start + 3600.0)
        assert len(sent) == 50
        assert b.held == 0
        # Never more than bytes_per_minute in any 60 s window.
        for t0, _ in sent:
            window = sum(len(i.frame) for t, i in sent if t0 <= t <= t0 + 60.0)
            assert window <= BYTES_PER_MINUTE
        # The first minute is full but not over, and goes to the new hostile tracks.
        first_minute = [i for t, i in sent if t < start + 60.0]
        assert sum(len(i.frame) for i in first_minute) > BYTES_PER_MINUTE - 100
        order = [(i.priority, i.hostility) for _, i in sent]
        assert order == sorted(order, key=lambda p: (p[0], p[1] != "hostile"))
        assert order[:35] == [(Priority.NEW, "hostile")] * 35
        assert order[35:40] == [(Priority.NEW, "suspect")] * 5
        assert order[40:] == [(Priority.UPDATE, "hostile")] * 10
        assert all(i.cdm.type == "UPPD" for _, i in sent[40:])
        c = b.counts
        assert c.sent == 60
        assert c.sent_new == 50
        assert c.sent_update == 10
        assert c.held_back >= 40  # most of the burst waited for the budget
        assert c.bytes_sent == sum(len(i.frame) for _, i in first + sent)


class TestWhatIsWorthSending:
    """Repeats suppressed, latest wins per track, lost and friendly tracks dropped."""

    def test_an_update_that_did_not_move_is_a_repeat(self) -> None:
        b = budget()
        b.offer(track(1))
        drain(b, 0.0, 10.0)
        assert b.offer(track(1, north_m=40.0, status="updated")) == "suppressed"
        assert b.held == 0
        assert b.counts.suppressed == 1
        assert b.offer(track(1, north_m=150.0, status="updated")) == "held"

    def test_a_newer_message_replaces_the_held_one_and_keeps_its_place(self) -> None:
        b = budget(burst_bytes=100, bytes_per_minute=200)  # one message at a time
        for n in (1, 2, 3):
            b.offer(track(n))
        first = b.next_due(0.0)
        assert first is not None
        assert first.track_id == "T-001"
        b.sent(first, 0.0)
        assert b.next_due(0.0) is None  # the bucket is spent: T-002 and T-003 wait
        assert b.offer(track(2, north_m=300.0, status="updated")) == "held"  # still new
        assert b.held == 2
        assert b.counts.superseded == 1
        sent = drain(b, 0.0, 600.0)
        assert [i.track_id for _, i in sent] == ["T-002", "T-003"]  # its place kept
        assert sent[0][1].cdm.type == "MAL"
        assert sent[0][1].lat_deg > LAT + 0.002  # the newer position went out

    def test_a_message_offered_while_the_first_was_on_its_way_is_weighed_again(self) -> None:
        b = budget()
        b.offer(track(1))
        b.offer(track(2))
        first = b.next_due(0.0)
        assert first is not None
        b.offer(track(1, north_m=500.0, status="updated"))  # while the MAL is being sent
        b.offer(track(2, north_m=10.0, status="updated"))
        b.sent(first, 0.0)
        second = b.next_due(0.0)
        assert second is not None
        assert second.track_id == "T-002"  # still the new target T-002 before T-001's update
        b.sent(second, 0.0)
        third = b.next_due(0.0)
        assert third is not None
        assert (third.track_id, third.priority, third.cdm.type) == (
            "T-001",
            Priority.UPDATE,
            "UPPD",
        )
        b.sent(third, 0.0)
        assert b.held == 0

    def test_a_lost_track_drops_its_held_message(self) -> None:
        b = budget(burst_bytes=100, bytes_per_minute=200)
        b.offer(track(1))
        assert b.offer(track(1, status="lost")) == "dropped_lost"
        assert b.held == 0
        assert b.wait_s(0.0) is None

    def test_a_merged_track_drops_its_held_message_like_a_lost_one(self) -> None:
        b = budget(burst_bytes=100, bytes_per_minute=200)
        b.offer(track(1))
        assert b.offer(track(1, status="merged")) == "dropped_lost"
        assert b.held == 0

    def test_hostilities_not_reported_are_counted_not_held(self) -> None:
        b = budget(report=frozenset({"hostile"}))
        assert b.offer(track(1, hostility="suspect")) == "not_reported"
        assert b.offer(track(2, hostility="friend")) == "not_reported"
        assert b.held == 0
        assert b.counts.not_reported == 2

    def test_a_track_no_longer_reported_drops_its_held_message(self) -> None:
        b = budget(burst_bytes=100, bytes_per_minute=200, report=frozenset({"hostile"}))
        b.offer(track(1))
        b.sent(b.next_due(0.0), 0.0)  # type: ignore[arg-type]
        b.offer(track(2))
        assert b.offer(track(2, hostility="suspect", status="updated")) == "not_reported"
        assert b.held == 0

    def test_a_new_track_takes_the_place_of_one_with_nothing_waiting(self) -> None:
        b = budget(max_tracks=3)
        for n in (1, 2, 3):
            b.offer(track(n))
        drain(b, 0.0, 600.0)
        b.offer(track(2, north_m=10.0, status="updated"))  # heard again: 1 is now the oldest
        assert b.offer(track(4)) == "held"
        assert b.counts.dropped_full == 0
        # Track 1 was forgotten: the net hears it again as a new target.
        assert b.offer(track(1, north_m=10.0, status="updated")) == "held"
        assert [i.cdm.type for _, i in drain(b, 600.0, 1200.0)] == ["MAL", "MAL"]

    def test_held_memory_is_bounded_by_max_tracks(self) -> None:
        b = budget(burst_bytes=100, bytes_per_minute=200, max_tracks=20)
        for n in range(500):
            b.offer(track(n, hostility="suspect" if n % 2 else "hostile"))
        assert b.held <= 20
        assert b.counts.dropped_full >= 480
        # What is left are the newest-remembered tracks, the hostile ones first in line.
        head = b._head()
        assert head is not None
        assert head.hostility == "hostile"


class _ScanningBudget(Budget):
    """The reference: make room by scanning every track (O(n) a new track), as first written."""

    def _forget_one(self, track: Track) -> bool:
        for track_id in self._known:
            if track_id not in self._held:
                del self._known[track_id]
                return True
        worst = max(self._held.values(), key=Outgoing.order)
        if (Priority.NEW, {"hostile": 0, "suspect": 1}[track.hostility]) > worst.order()[:2]:
            return False
        del self._held[worst.track_id]
        del self._known[worst.track_id]
        self.counts.dropped_full += 1
        return True


_steps = st.lists(
    st.tuples(
        st.integers(0, 11),  # which track
        st.sampled_from(["hostile", "suspect", "lost", "send"]),
        st.integers(0, 3),  # how far it moved, in 150 m steps
    ),
    max_size=120,
)


class TestMakingRoom:
    """At ``max_tracks`` a new track makes room in O(log n), choosing as a full scan would."""

    @given(_steps)
    @settings(max_examples=150, deadline=None)
    def test_the_same_tracks_are_kept_and_held_as_by_a_full_scan(
        self, steps: list[tuple[int, str, int]]
    ) -> None:
        options: dict[str, object] = {
            "bytes_per_minute": BYTES_PER_MINUTE,
            "burst_bytes": 260,
            "min_move_m": 100.0,
            "max_tracks": 4,
            "report": frozenset({"hostile", "suspect"}),
            "now": 0.0,
        }
        fast, reference = Budget(encode, **options), _ScanningBudget(encode, **options)  # type: ignore[arg-type]
        now = 0.0
        for n, what, moved in steps:
            for b in (fast, reference):
                if what == "send":
                    item = b.next_due(now)
                    if item is not None:
                        b.sent(item, now)
                elif what == "lost":
                    b.offer(track(n, status="lost"))
                else:
                    b.offer(track(n, north_m=150.0 * moved, hostility=what, status="updated"))
            now += 7.0
            assert list(fast._known) == list(reference._known)
            assert {k: i.frame for k, i in fast._held.items()} == {
                k: i.frame for k, i in reference._held.items()
            }
            assert fast.counts == reference.counts
