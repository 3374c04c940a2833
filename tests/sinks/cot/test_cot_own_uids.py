"""The uids the cot sink reports for our own airframes are those its CoT carries when read back.

The gateway refuses a source's friendly report under such a uid (our own airframe heard back on
a mesh the gateway also listens on, a TAK server relaying everything, or a forgery), so
``CotSink.own_uids`` must agree with what the builder writes and the CoT parser reads.
"""

from __future__ import annotations

from datetime import UTC, datetime

from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.events import Position, Telemetry
from sinks.cot.codec import to_xml
from sinks.cot.event import build
from sinks.cot.sink import CotSink, CotSinkConfig
from sinks.cot.validate import parse_cot

AIRFRAME = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}", fullmatch=True)


@settings(max_examples=50, deadline=None)
@given(airframe=AIRFRAME, prefix=st.sampled_from(["fischer-", "BDE2.", ""]))
def test_own_uids_are_the_uids_our_airframes_are_read_back_under(
    airframe: str, prefix: str
) -> None:
    config = CotSinkConfig.model_validate(
        {"destinations": [{"uri": "udp://127.0.0.1:9"}], "uid_prefix": prefix}
    )
    sink = CotSink("tak", config)
    now = datetime.now(UTC)
    telemetry = Telemetry(
        event_id="t",
        airframe=airframe,
        time=now,
        position=Position(lat_deg=65.8, lon_deg=21.7, alt_msl_m=600.0),
        gps_fix_type=3,
    )
    cot = build(telemetry, sink.options)
    assert cot is not None
    assert sink.own_uids([airframe]) == frozenset({parse_cot(to_xml(cot)).uid})
