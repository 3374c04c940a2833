"""The AES-256-GCM tunnel: day keys, tamper detection, replay, rotation around midnight."""

from __future__ import annotations

from datetime import UTC, date, datetime, timedelta

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.errors import AuthenticationFailed, FrameError, Malformed, Replayed
from gateway.fleet.security.tunnel import DayKeys, Sealer, TunnelOpener, derive_day_key
from gateway.testing import fuzz_examples

MASTER = bytes(range(32))
NOON = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)


class Clock:
    def __init__(self, now: datetime) -> None:
        self.now = now

    def __call__(self) -> datetime:
        return self.now


def pair(now: datetime = NOON, **opener_kw: float) -> tuple[Sealer, TunnelOpener, Clock]:
    clock = Clock(now)
    keys = DayKeys(master=MASTER)
    sealer = Sealer("F26E-001", keys, clock)
    opener = TunnelOpener(keys, frozenset({"F26E-001"}), clock, **opener_kw)
    return sealer, opener, clock


class TestSealOpen:
    """Round trip, and what an airframe holding only its day keys can do."""

    def test_round_trip(self) -> None:
        sealer, opener, _ = pair()
        opened = opener.open_frame(sealer.seal(b"\xfd mavlink frame"))
        assert (opened.airframe, opened.payload, opened.key_day) == (
            "F26E-001",
            b"\xfd mavlink frame",
            date(2026, 11, 22),
        )

    def test_airframe_with_only_its_day_keys_talks_to_the_master_holder(self) -> None:
        clock = Clock(NOON)
        day = NOON.date()
        own = DayKeys(keys={("F26E-001", day): derive_day_key(MASTER, "F26E-001", day)})
        sealer = Sealer("F26E-001", own, clock)
        opener = TunnelOpener(DayKeys(master=MASTER), frozenset({"F26E-001"}), clock)
        assert opener.open_frame(sealer.seal(b"x")).payload == b"x"
        with pytest.raises(AuthenticationFailed, match="no day key"):
            Sealer("F26E-001", own, Clock(NOON + timedelta(days=1))).seal(b"x")

    def test_day_keys_differ_per_day_and_airframe(self) -> None:
        d = date(2026, 11, 22)
        keys = {
            derive_day_key(MASTER, "A", d),
            derive_day_key(MASTER, "B", d),
            derive_day_key(MASTER, "A", d + timedelta(days=1)),
        }
        assert len(keys) == 3
        assert all(len(k) == 32 for k in keys)

    def test_nonces_never_repeat_within_a_session(self) -> None:
        sealer, _, _ = pair()
        nonces = {sealer.seal(b"x")[-16 - 1 - 12 : -16 - 1] for _ in range(2000)}
        assert len(nonces) == 2000


class TestFailClosed:
    """Every way a frame can be wrong is rejected with its reason."""

    @settings(max_examples=500, deadline=None)
    @given(st.data())
    def test_any_flipped_bit_is_rejected(self, data: st.DataObject) -> None:
        sealer, opener, _ = pair()
        frame = bytearray(sealer.seal(b"\xfd\x09\x00\x00\x00\x01\x01payload"))
        bit = data.draw(st.integers(min_value=0, max_value=len(frame) * 8 - 1))
        frame[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(FrameError):
            opener.open_frame(bytes(frame))

    def test_replayed_frame_is_rejected(self) -> None:
        sealer, opener, _ = pair()
        frame = sealer.seal(b"x")
        opener.open_frame(frame)
        with pytest.raises(Replayed):
            opener.open_frame(frame)

    def test_out_of_order_inside_window_is_accepted_once(self) -> None:
        sealer, opener, _ = pair()
        frames = [sealer.seal(bytes([i])) for i in range(5)]
        for i in (0, 3, 1, 4, 2):
            assert opener.open_frame(frames[i]).payload == bytes([i])
        with pytest.raises(Replayed):
            opener.open_frame(frames[2])

    def test_frame_behind_the_window_is_rejected(self) -> None:
        sealer, opener, _ = pair()
        old = sealer.seal(b"old")
        for _ in range(1100):
            opener.open_frame(sealer.seal(b"new"))
        with pytest.raises(Replayed):
            opener.open_frame(old)

    def test_stale_frame_is_rejected_after_freshness(self) -> None:
        sealer, opener, clock = pair()
        frame = sealer.seal(b"x")
        clock.now += timedelta(seconds=31)
        with pytest.raises(Replayed, match="freshness"):
            opener.open_frame(frame)

    def test_forged_frame_does_not_advance_the_window(self) -> None:
        sealer, opener, _ = pair()
        genuine = sealer.seal(b"x")
        forged = bytearray(genuine)
        forged[-20] ^= 0xFF  # ciphertext byte: tag fails
        with pytest.raises(AuthenticationFailed):
            opener.open_frame(bytes(forged))
        assert opener.open_frame(genuine).payload == b"x"

    def test_unknown_airframe_and_garbage(self) -> None:
        clock = Clock(NOON)
        keys = DayKeys(master=MASTER)
        stranger = Sealer("F26E-999", keys, clock)
        opener = TunnelOpener(keys, frozenset({"F26E-001"}), clock)
        with pytest.raises(AuthenticationFailed, match="unknown airframe"):
            opener.open_frame(stranger.seal(b"x"))
        with pytest.raises(Malformed):
            opener.open_frame(b"\xfd\x09not a tunnel frame at all")

    @settings(max_examples=fuzz_examples(1000), deadline=None)
    @given(st.binary(max_size=300))
    def test_arbitrary_bytes_raise_only_frame_errors(self, blob: bytes) -> None:
        _, opener, _ = pair()
        with pytest.raises(FrameError):
            opener.open_frame(b"F6\x01" + blob)
        with pytest.raises(FrameError):
            opener.open_frame(blob)


class TestRotation:
    """Key days around 00:00 UTC: grace for yesterday, skew for tomorrow."""

    def test_yesterdays_key_accepted_only_inside_grace(self) -> None:
        before = datetime(2026, 11, 22, 23, 59, 50, tzinfo=UTC)
        sealer, opener, clock = pair(before, grace_s=600, freshness_s=10_000)
        frame = sealer.seal(b"late")
        clock.now = before + timedelta(minutes=5)  # 00:04:50, inside the 10 min grace
        assert opener.open_frame(frame).key_day == date(2026, 11, 22)
        frame2 = sealer.seal(b"later")  # sealer's clock moved too: seals with the new day
        assert opener.open_frame(frame2).key_day == date(2026, 11, 23)
        clock.now = before
        old = sealer.seal(b"old")
        clock.now = before + timedelta(minutes=11)
        with pytest.raises(AuthenticationFailed, match="key day"):
            opener.open_frame(old)

    def test_tomorrows_key_accepted_only_inside_skew(self) -> None:
        after = datetime(2026, 11, 23, 0, 0, 30, tzinfo=UTC)
        sealer, opener, clock = pair(after, skew_s=120, freshness_s=10_000)
        early = sealer.seal(b"fast clock")
        clock.now = after - timedelta(seconds=60)
        assert opener.open_frame(early).key_day == date(2026, 11, 23)
        clock.now = after - timedelta(minutes=10)
        with pytest.raises(AuthenticationFailed):
            opener.open_frame(early)


class TestMemory:
    """What the opener remembers per frame is bounded, and remembering changes no decision."""

    def test_a_header_seen_before_still_has_its_key_day_judged(self) -> None:
        sealer, opener, clock = pair(freshness_s=10 * 86_400)
        first = sealer.seal(b"a")
        second = sealer.seal(b"b")
        assert opener.open_frame(first).payload == b"a"  # its header is remembered now
        clock.now = NOON + timedelta(days=2)
        with pytest.raises(AuthenticationFailed, match="key day"):
            opener.open_frame(second)

    def test_headers_of_unknown_airframes_and_refused_days_are_not_remembered(self) -> None:
        _, opener, clock = pair()
        stranger = Sealer("F26E-999", DayKeys(master=MASTER), clock)
        for _ in range(10):
            with pytest.raises(AuthenticationFailed, match="unknown airframe"):
                opener.open_frame(stranger.seal(b"x"))
        old = Sealer("F26E-001", DayKeys(master=MASTER), Clock(NOON - timedelta(days=3)))
        with pytest.raises(AuthenticationFailed, match="key day"):
            opener.open_frame(old.seal(b"x"))
        assert opener._headers == {}

    def test_a_frame_on_a_second_link_passes_only_within_cross_link_s(
        self, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        mono = [100.0]
        monkeypatch.setattr("gateway.fleet.security.tunnel.time.monotonic", lambda: mono[0])
        sealer, opener, _ = pair(cross_link_s=1.0)
        redundant, replayed = sealer.seal(b"r"), sealer.seal(b"p")
        assert opener.open_frame(redundant, "a").payload == b"r"
        assert opener.open_frame(replayed, "a").payload == b"p"
        mono[0] += 0.5
        assert opener.open_frame(redundant, "b").payload == b"r"  # the same frame on both links
        mono[0] += 1.0
        with pytest.raises(Replayed, match="another link"):
            opener.open_frame(replayed, "b")

    def test_nonces_remembered_across_links_are_capped_and_forgotten_when_stale(
        self, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        mono = [100.0]
        monkeypatch.setattr("gateway.fleet.security.tunnel.time.monotonic", lambda: mono[0])
        monkeypatch.setattr("gateway.fleet.security.tunnel._MAX_ACCEPTED", 2048)
        sealer, opener, _ = pair(freshness_s=30)
        for _ in range(5000):
            opener.open_frame(sealer.seal(b"x"), "a")
            assert len(opener._accepted["F26E-001"]) < 2048 + 1024
        mono[0] += 61  # twice the freshness window: every nonce so far is stale
        for _ in range(1024):
            opener.open_frame(sealer.seal(b"x"), "a")
        assert len(opener._accepted["F26E-001"]) <= 1024
