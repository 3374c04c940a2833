"""The stream deframer: frames split anywhere, garbage between them, fuzzed input."""

from __future__ import annotations

from datetime import UTC, datetime

from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.fleet.deframe import StreamDeframer, frame_for_stream
from gateway.fleet.security.tunnel import DayKeys, Opened, Sealer, TunnelOpener
from gateway.testing import fuzz_examples

NOW = datetime(2026, 11, 22, 12, tzinfo=UTC)
KEYS = DayKeys(master=bytes(range(32)))


def make() -> tuple[Sealer, TunnelOpener]:
    clock = lambda: NOW  # noqa: E731 - a fixed clock
    return Sealer("A", KEYS, clock), TunnelOpener(KEYS, frozenset({"A"}), clock)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.binary(min_size=1, max_size=200), min_size=1, max_size=10),
    st.lists(st.binary(max_size=50), min_size=11, max_size=11),
    st.lists(st.integers(min_value=1, max_value=64), min_size=1, max_size=20),
)
def test_frames_survive_garbage_and_arbitrary_splits(
    payloads: list[bytes], garbage: list[bytes], cuts: list[int]
) -> None:
    sealer, opener = make()
    stream = garbage[0] + b"".join(
        frame_for_stream(sealer.seal(p)) + garbage[i + 1] for i, p in enumerate(payloads)
    )
    deframer = StreamDeframer()
    got: list[Opened] = []
    pos, i = 0, 0
    while pos < len(stream):
        step = cuts[i % len(cuts)]
        got += deframer.feed(stream[pos : pos + step], lambda f: opener.open_frame(f, "s"))
        pos, i = pos + step, i + 1
    received = [o.payload for o in got]
    # Garbage never forges a frame, and frames keep their order.
    assert received == [p for p in payloads if p in received]
    if not any(b"F6" in g for g in garbage):
        # Only garbage holding the magic can look like a header and swallow a real frame.
        assert received == payloads


@settings(max_examples=fuzz_examples(500), deadline=None)
@given(st.binary(max_size=3000))
def test_arbitrary_bytes_never_raise_and_stay_bounded(blob: bytes) -> None:
    _, opener = make()
    deframer = StreamDeframer(max_frame_bytes=512)
    assert deframer.feed(blob, lambda f: opener.open_frame(f, "s")) == []
    assert len(deframer._buf) <= 512 + 2


def test_clean_stream_opens_every_frame() -> None:
    sealer, opener = make()
    stream = b"".join(frame_for_stream(sealer.seal(bytes([n]) * 30)) for n in range(50))
    deframer = StreamDeframer()
    got = deframer.feed(stream, lambda f: opener.open_frame(f, "s"))
    assert [o.payload[0] for o in got] == list(range(50))
    assert deframer.skipped_bytes == 0
