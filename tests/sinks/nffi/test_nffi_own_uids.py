"""The uids the nffi sink reports for our own airframes are those its tracks get when read back.

The gateway refuses a source's friendly report under such a uid (our own airframe echoed by a
C2 system), so ``NffiSink.own_uids`` must agree with what the encoder writes and the parser
reads, whatever the airframe's name and the sink's options.
"""

from __future__ import annotations

from datetime import UTC, datetime

from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.events import Position, Telemetry
from sinks.nffi.codec import encode_message, parse_message, tracks_of
from sinks.nffi.sink import NffiSink, NffiSinkConfig

AIRFRAME = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}", fullmatch=True)


@settings(max_examples=50, deadline=None)
@given(
    airframe=AIRFRAME,
    country=st.none() | st.sampled_from(["SWE", "NOR"]),
    subsystem=st.none() | st.sampled_from(["NODE-1", "BDE.2"]),
)
def test_own_uids_are_the_uids_our_tracks_are_read_back_under(
    airframe: str, country: str | None, subsystem: str | None
) -> None:
    options: dict[str, object] = {"path": "/dev/null", "system": "FISCHER-GW"}
    if country is not None:
        options["country"] = country
    if subsystem is not None:
        options["subsystem"] = subsystem
    sink = NffiSink("c2", NffiSinkConfig.model_validate(options))
    telemetry = Telemetry(
        event_id="t",
        airframe=airframe,
        time=datetime(2026, 11, 25, 12, 0, 0, tzinfo=UTC),
        position=Position(lat_deg=65.8, lon_deg=21.7, alt_msl_m=250.0),
    )
    tracks = tracks_of([telemetry], sink.options)
    (track,) = parse_message(encode_message(tracks)).tracks
    assert sink.own_uids([airframe]) == frozenset({track.uid})
