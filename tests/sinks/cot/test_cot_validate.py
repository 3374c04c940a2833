"""Our CoT validator refuses what receivers drop and the available decoders let through."""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from test_cot_event import TELEMETRY, options

from gateway.errors import FrameError
from gateway.testing import fuzz_examples
from sinks.cot.codec import to_proto, to_xml
from sinks.cot.event import build
from sinks.cot.proto import ProtoError, mesh_frame, mesh_payload, read_fields, stream_frame
from sinks.cot.validate import CotError, TakControl, parse_cot, scan_control

takproto = pytest.importorskip("takproto")

CORPUS = Path(__file__).resolve().parents[3].parent / "shared" / "corpus" / "cot"


def good() -> bytes:
    event = build(TELEMETRY, options())
    assert event is not None
    return to_xml(event)


class TestRules:
    """Each rule names what was wrong, with a short problem code for counters."""

    def test_latitude_91_is_refused_though_takproto_accepts_it(self) -> None:
        bad = good().replace(b'lat="58.4108123"', b'lat="91.0"')
        assert takproto.parse_proto(bytearray(bad)) is not None
        with pytest.raises(CotError, match="off the globe") as caught:
            parse_cot(bad)
        assert caught.value.problem == "position"
        assert isinstance(caught.value, FrameError)

    def test_missing_point_is_refused_though_takproto_accepts_it(self) -> None:
        bad = good().replace(b"<point", b"<nopoint")
        assert takproto.parse_proto(bytearray(bad)) is not None
        with pytest.raises(CotError, match="exactly one <point>"):
            parse_cot(bad)

    @pytest.mark.parametrize(
        ("old", "new", "problem"),
        [
            (b'how="m-g"', b'how=""', "attribute"),
            (b'how="m-g"', b'how="m g"', "how"),
            (b'type="a-f-A-M-F-Q"', b'type="a f"', "type"),
            (b'version="2.0"', b'version="1.9"', "version"),
            (b'version="2.0"', b'version="2.0" qos="high"', "qos"),
            (b'Z" start', b'+00:00" start', "time"),
            (b'time="2026-11-22T10', b'time="2026-13-22T10', "time"),
            (b'stale="2026-11-22T10:15:45', b'stale="2026-11-22T10:15:30', "stale"),
            (b'hae="612.4"', b'hae="NaN"', "point"),
            (b'hae="612.4"', b'hae="6e2"', "point"),
            (b'ce="4.5"', b'ce="-4.5"', "point"),
            (b'lat="58.4108123"', 'lat="\u0665"'.encode(), "point"),
            (b"<event ", b"<evnt ", "xml"),
            (b"<?xml", b"<?xml version='1.0'?><wrapper/><!-- --><?x", "xml"),
        ],
    )
    def test_broken_events_name_the_problem(self, old: bytes, new: bytes, problem: str) -> None:
        with pytest.raises(CotError) as caught:
            parse_cot(good().replace(old, new, 1))
        assert caught.value.problem == problem

    @pytest.mark.parametrize(
        ("data", "problem"),
        [
            (b'<?xml version="1.0"?>\n<event version="2.0"/>\n', "framing"),
            (b'<event version="2.0"/>', "framing"),
        ],
    )
    def test_strict_mode_adds_our_own_framing_rules(self, data: bytes, problem: str) -> None:
        with pytest.raises(CotError) as caught:
            parse_cot(data, strict=True)
        assert caught.value.problem == problem

    def test_strict_mode_wants_milliseconds_and_no_whitespace_in_uid(self) -> None:
        assert parse_cot(good(), strict=True).uid == "fischer-F26E-007"
        with pytest.raises(CotError, match="3 fraction digits"):
            parse_cot(good().replace(b'.250Z" start', b'Z" start'), strict=True)
        with pytest.raises(CotError, match="whitespace"):
            parse_cot(good().replace(b'uid="fischer-F26E-007"', b'uid="a b"'), strict=True)

    @pytest.mark.parametrize(
        "bomb",
        [
            b'<?xml version="1.0"?><!DOCTYPE e [<!ENTITY a "aaaa">]><event/>',
            b'<?xml version="1.0"?><!DOCTYPE e SYSTEM "http://example.invalid/e.dtd"><event/>',
            '<?xml version="1.0" encoding="UTF-16"?><!DOCTYPE e [<!ENTITY a "a">]><event/>'.encode(
                "utf-16"
            ),
        ],
    )
    def test_dtds_and_entities_are_refused_before_anything_expands(self, bomb: bytes) -> None:
        with pytest.raises(CotError) as caught:
            parse_cot(bomb)
        assert caught.value.problem == "dtd"

    def test_oversize_is_refused_unread(self) -> None:
        with pytest.raises(CotError, match="exceeds"):
            parse_cot(b" " * (64 * 1024 + 1))


class TestProtobuf:
    """TAK protocol v1 messages are read by our own bounded decoder and validated the same way."""

    def test_mesh_and_stream_frames_parse(self) -> None:
        event = build(TELEMETRY, options())
        assert event is not None
        for data in (mesh_frame(to_proto(event)), stream_frame(to_proto(event))):
            parsed = parse_cot(data)
            assert (parsed.uid, parsed.encoding) == (event.uid, "protobuf")
            assert (parsed.lat, parsed.callsign, parsed.stale) == (
                event.lat, event.callsign, event.stale.replace(microsecond=250000),
            )  # fmt: skip

    def test_takproto_encoded_events_parse(self) -> None:
        message = takproto.xml2proto(good(), takproto.TAKProtoVer.MESH)
        assert parse_cot(bytes(message)).uid == "fischer-F26E-007"

    def test_latitude_91_in_protobuf_is_refused(self) -> None:
        message = takproto.xml2proto(
            good().replace(b'lat="58.4108123"', b'lat="91"'), takproto.TAKProtoVer.MESH
        )
        with pytest.raises(CotError, match="off the globe"):
            parse_cot(bytes(message))

    def test_wintak_geochat_from_the_corpus_parses(self) -> None:
        path = CORPUS / "takprotobuf" / "tmp.bin"
        if not path.exists():
            pytest.skip("shared corpus absent")
        parsed = parse_cot(path.read_bytes())
        assert (parsed.type, parsed.how, parsed.hae) == ("b-t-f", "h-g-i-g-o", 9999999.0)

    def test_control_only_message_is_not_an_event(self) -> None:
        control = b"\x0a\x04\x08\x01\x10\x01"  # TakMessage{takControl{min 1, max 1}}
        with pytest.raises(CotError) as caught:
            parse_cot(mesh_frame(control))
        assert caught.value.problem == "not_event"

    @pytest.mark.parametrize(
        ("data", "message"),
        [
            (b"\xbf\x05\x12", "claims 5 bytes"),
            (b"\xbf\x01\xbf\x12\x7f", "claims 127 bytes"),
            (b"\xbf\x01\xbf\x0b", "wire type 3"),
            (b"\xbf\x01\xbf\x08" + b"\xff" * 11, "varint"),
            (b"\xbf\x01\xbf\x00", "field number 0"),
        ],
    )
    def test_malformed_protobuf_is_named(self, data: bytes, message: str) -> None:
        with pytest.raises(CotError, match=message):
            parse_cot(data)

    def test_proto_reader_rejects_truncation(self) -> None:
        with pytest.raises(ProtoError, match="truncated"):
            read_fields(b"\x09\x00\x00")
        with pytest.raises(ProtoError, match="magic"):
            mesh_payload(b"\x00")


class TestControl:
    """The TAK negotiation events a client has to recognise."""

    @pytest.mark.parametrize(
        ("detail", "type_", "expected"),
        [
            (
                b'<TakControl><TakProtocolSupport version="1"/></TakControl>',
                b"v",
                TakControl.OFFER_V1,
            ),
            (b'<TakControl><TakProtocolSupport version="2"/></TakControl>', b"v", TakControl.NONE),
            (b'<TakControl><TakResponse status="true"/></TakControl>', b"r", TakControl.ACCEPTED),
            (b'<TakControl><TakResponse status="false"/></TakControl>', b"r", TakControl.REFUSED),
            (b"", b"r", TakControl.REFUSED),
        ],
    )
    def test_offer_and_response(self, detail: bytes, type_: bytes, expected: TakControl) -> None:
        event = (
            b'<?xml version="1.0"?>\n<event version="2.0" uid="protouid" type="t-x-takp-' + type_
            + b'" time="2026-11-22T10:00:00Z" start="2026-11-22T10:00:00Z" '
            b'stale="2026-11-22T10:01:00Z" how="m-g"><point lat="0.0" lon="0.0" hae="0.0" '
            b'ce="999999" le="999999"/><detail>' + detail + b"</detail></event>"
        )  # fmt: skip
        assert scan_control(event) is expected

    @given(st.binary(max_size=500))
    @settings(max_examples=fuzz_examples(200), deadline=None)
    def test_anything_else_is_none(self, blob: bytes) -> None:
        assert scan_control(blob + b"t-x-takp-v") in (TakControl.NONE, TakControl.OFFER_V1)


_XML_PIECES = st.sampled_from(
    [b"<event", b"</event>", b"<point", b"/>", b">", b'"', b" lat=", b" uid=", b"<detail>",
     b"<!DOCTYPE", b"<!ENTITY", b"&a;", b"<?xml", b"\xbf\x01\xbf", b"\xbf", b"\x00", b"\xff",
     b' version="2.0"', b' type="a-f-G"', b' how="m-g"', b' time="2026-11-22T10:00:00Z"',
     b' start="2026-11-22T10:00:00Z"', b' stale="2026-11-22T10:05:00Z"', b' hae="1"',
     b' lon="1"', b' ce="1"', b' le="1"', b"\x12", b"\x0a", b"\x08\x96\x01"]
)  # fmt: skip


class TestFuzz:
    """Whatever comes in, only CotError comes out."""

    @settings(max_examples=fuzz_examples(400), deadline=None)
    @given(st.binary(max_size=2000))
    @example(b"\xbf\x01\xbf")
    @example(b'<?xml version="1.0" encoding="nope"?><event/>')
    def test_arbitrary_bytes(self, blob: bytes) -> None:
        with contextlib.suppress(CotError):
            parse_cot(blob)

    @settings(max_examples=fuzz_examples(400), deadline=None)
    @given(st.lists(_XML_PIECES | st.binary(max_size=8), max_size=40).map(b"".join))
    def test_structured_fragments(self, blob: bytes) -> None:
        with contextlib.suppress(CotError):
            parse_cot(blob)

    @settings(max_examples=fuzz_examples(300), deadline=None)
    @given(st.integers(0, 600), st.binary(min_size=1, max_size=4))
    def test_mutations_of_a_valid_event(self, position: int, patch: bytes) -> None:
        data = bytearray(good())
        data[position : position + len(patch)] = patch
        with contextlib.suppress(CotError):
            parse_cot(bytes(data))
        proto = bytearray(mesh_frame(to_proto(build(TELEMETRY, options()))))  # type: ignore[arg-type]
        proto[position % len(proto) : position % len(proto) + len(patch)] = patch
        with contextlib.suppress(CotError):
            parse_cot(bytes(proto))
