"""The decode fast path against pymavlink: same layouts, same fields, same frames refused.

pymavlink is the reference throughout: its generated classes for the layouts, its packer
and checksum for the frames, and the gateway's ``MavlinkParser`` (pymavlink underneath) for
what is accepted. Generated frames cover every message of ``GATEWAY_MESSAGES`` (random
values and bytes, extensions present or cut, MAVLink 1 and 2, signed, corrupted); the
corpus test replays every frame of every tlog in ../shared/corpus when it is there.
"""

from __future__ import annotations

import math
import random
import struct
import time
import tomllib
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

import pytest
import structlog
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as apm
from pymavlink.generator.mavcrc import x25crc

from gateway.errors import Malformed
from gateway.fleet import fastdecode
from gateway.fleet.commander import FleetCommander
from gateway.fleet.fastdecode import (
    GATEWAY_MESSAGES,
    PYMAVLINK_CHECKED,
    FastDecoder,
    FastMessage,
    default_decoder,
    load_messages,
)
from gateway.fleet.hopschedule import HopSchedules
from gateway.fleet.mavlink import MavlinkParser
from gateway.fleet.mavxml import pymavlink_xml_dir, read_dialect, x25_crc
from gateway.ops.instruments import Instruments
from gateway.sim.airframe import SimProfile, SimulatedAirframe
from gateway.testing import fuzz_examples
from tests.gateway.fleet.test_ingest import T0, make_ingest

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
CORPUS = ROOT.parent / "shared" / "corpus" / "mavlink"
#: Every message pymavlink decodes in the gateway (ardupilotmega and the project dialect).
PYMAVLINK = dict(apm.mavlink_map)
BY_NAME = {cls.msgname: cls for cls in PYMAVLINK.values()}
CHOSEN = sorted(GATEWAY_MESSAGES)


def pymavlink_decode(frame: bytes) -> Any | None:
    """pymavlink's message if the gateway's parser accepts ``frame`` as one whole frame."""
    parser = MavlinkParser()
    try:
        messages = parser.feed(frame, whole=True)
    except Malformed:
        return None
    if len(messages) != 1 or parser.bad or parser.unknown or parser.truncated:
        return None
    return messages[0]


def same(a: Any, b: Any) -> bool:
    """Equal values of equal types; floats bit for bit (so NaN equals the same NaN)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return struct.pack("<d", a) == struct.pack("<d", b)
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return bool(a == b)


def assert_same_message(fast: FastMessage, reference: Any) -> None:
    assert fast.get_type() == reference.get_type()
    assert fast.get_msgId() == reference.get_msgId()
    assert fast.fieldnames == tuple(reference.fieldnames)
    for name in reference.fieldnames:
        mine, theirs = getattr(fast, name), getattr(reference, name)
        assert same(mine, theirs), f"{fast.get_type()}.{name}: {mine!r} != {theirs!r}"
    assert fast.get_srcSystem() == reference.get_srcSystem()
    assert fast.get_srcComponent() == reference.get_srcComponent()
    assert fast.get_seq() == reference.get_seq()
    assert bytes(fast.get_msgbuf()) == bytes(reference.get_msgbuf())


def check_agreement(decoder: FastDecoder, frame: bytes) -> str:
    """Decode ``frame`` both ways and assert they agree; returns what happened."""
    reference = pymavlink_decode(frame)
    try:
        fast = decoder.decode(frame)
    except Malformed:
        assert reference is None, f"fast path refused what pymavlink took: {reference}"
        return "both refused"
    if fast is None:
        # Deferred to pymavlink: only for frames that are not one of the decoder's messages.
        assert reference is None or reference.get_msgId() not in decoder
        return "deferred"
    assert reference is not None, f"fast path took what pymavlink refused: {fast!r}"
    assert_same_message(fast, reference)
    return "both took"


def frame_of(
    msgid: int,
    payload: bytes,
    *,
    v1: bool = False,
    signature: bytes | None = None,
    header: tuple[int, int, int, int] = (0, 7, 1, 1),
    crc_extra: int | None = None,
) -> bytes:
    """A frame around ``payload``, checksummed with pymavlink's CRC and CRC_EXTRA."""
    compat, seq, sysid, compid = header
    if v1:
        head = bytes([0xFE, len(payload), seq, sysid, compid, msgid])
    else:
        flags = 0x01 if signature is not None else 0
        head = bytes([0xFD, len(payload), flags, compat, seq, sysid, compid])
        head += msgid.to_bytes(3, "little")
    crc = x25crc(head[1:] + payload)
    extra = PYMAVLINK[msgid].crc_extra if crc_extra is None else crc_extra
    crc.accumulate(bytes([extra]))
    return head + payload + struct.pack("<H", crc.crc) + (signature or b"")


# -- layouts ------------------------------------------------------------------------------


def test_every_message_layout_from_the_xml_equals_pymavlinks_class() -> None:
    """CRC_EXTRA, struct format and both field orders of all 300-odd messages, not just ours."""
    xml_dir = pymavlink_xml_dir()
    defs = read_dialect(xml_dir / "ardupilotmega.xml")
    defs.update(read_dialect(ROOT / "gateway" / "fleet" / "fischer_dialect.xml", [xml_dir]))
    assert len(PYMAVLINK) > 300
    for msgid, cls in PYMAVLINK.items():
        message = defs[msgid]
        assert message.name == cls.msgname
        assert message.crc_extra == cls.crc_extra, message.name
        assert message.struct_format == cls.unpacker.format, message.name
        assert [f.name for f in message.fields] == list(cls.fieldnames), message.name
        assert [f.name for f in message.wire_fields] == list(cls.ordered_fieldnames)


def test_the_checksum_is_pymavlinks() -> None:
    rng = random.Random(24)
    for size in (0, 1, 2, 17, 255, 300):
        data = rng.randbytes(size)
        start = rng.randrange(0x10000)
        crc = x25crc()
        crc.crc = start
        crc.accumulate(data)
        assert x25_crc(data, start) == crc.crc


def test_the_installed_pymavlink_is_the_one_checked_and_every_message_is_built() -> None:
    """The pin: another pymavlink turns the fast path off until it is checked again."""
    assert metadata.version("pymavlink") == PYMAVLINK_CHECKED
    decoder = default_decoder()
    assert {m.name for m in decoder.messages.values()} == GATEWAY_MESSAGES


def test_pyproject_pins_the_pymavlink_that_was_checked() -> None:
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert f"pymavlink=={PYMAVLINK_CHECKED}" in pyproject["project"]["dependencies"]


def test_another_pymavlink_turns_the_fast_path_off(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(fastdecode.metadata, "version", lambda _name: "2.4.99")
    with structlog.testing.capture_logs() as logs:
        decoder = default_decoder.__wrapped__()
    assert not decoder.messages
    frame = apm.MAVLink(None).heartbeat_encode(1, 3, 0, 0, 4).pack(apm.MAVLink(None))
    assert decoder.decode(bytes(frame)) is None
    assert logs[0]["event"] == "fastdecode_disabled"
    assert logs[0]["installed"] == "2.4.99"


def test_pymavlink_told_to_ignore_crcs_turns_the_fast_path_off(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """pymavlink reads MAV_IGNORE_CRC at import; the fast path never accepts a bad CRC."""
    monkeypatch.setenv("MAV_IGNORE_CRC", "1")
    with structlog.testing.capture_logs() as logs:
        assert not default_decoder.__wrapped__().messages
    assert logs[0]["reason"] == "mav_ignore_crc"


def test_the_chosen_messages_are_the_ones_the_gateway_handles() -> None:
    """Every message with a handler (ingest, session, commander, hop schedules) is fast;
    the two the gateway only sends are there for the dialect's sake."""
    ingest, _events, _inst = make_ingest(1)
    sessions = ingest.sessions
    FleetCommander(sessions, lambda _airframe: True)
    HopSchedules(sessions.values(), lambda _event: True, Instruments(), lambda: T0)
    (session,) = sessions.values()
    handled = {name for name in BY_NAME if session.handlers(name)}
    assert handled == GATEWAY_MESSAGES - {"FISCHER_DETECTION_ACK", "FISCHER_HOP_SCHEDULE"}


def test_a_message_unknown_to_the_xml_is_named() -> None:
    with pytest.raises(ValueError, match="NOT_A_MESSAGE"):
        load_messages(["HEARTBEAT", "NOT_A_MESSAGE"])


# -- generated frames -------------------------------------------------------------------


def field_values(cls: Any) -> st.SearchStrategy[list[Any]]:
    """Random values for each field of pymavlink's ``cls``, in constructor order."""
    ints = {
        "int8_t": (-(1 << 7), (1 << 7) - 1),
        "uint8_t": (0, (1 << 8) - 1),
        "int16_t": (-(1 << 15), (1 << 15) - 1),
        "uint16_t": (0, (1 << 16) - 1),
        "int32_t": (-(1 << 31), (1 << 31) - 1),
        "uint32_t": (0, (1 << 32) - 1),
        "int64_t": (-(1 << 63), (1 << 63) - 1),
        "uint64_t": (0, (1 << 64) - 1),
    }
    strategies: list[st.SearchStrategy[Any]] = []
    for name, kind in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        length = cls.array_lengths[list(cls.ordered_fieldnames).index(name)]
        if kind == "char":
            strategies.append(
                st.binary(min_size=1, max_size=1) if not length else st.binary(max_size=length)
            )
            continue
        if kind in ("float", "double"):
            one: st.SearchStrategy[Any] = st.floats(width=32 if kind == "float" else 64)
        else:
            low, high = ints[kind.replace("_mavlink_version", "")]
            one = st.integers(low, high) | st.just(0)
        strategies.append(st.lists(one, min_size=length, max_size=length) if length else one)
    return st.tuples(*strategies).map(list)


@st.composite
def packed_frames(draw: st.DrawFn) -> bytes:
    """A frame pymavlink packs from random values (it drops a MAVLink 2 zero tail itself)."""
    cls = BY_NAME[draw(st.sampled_from(CHOSEN))]
    mav = apm.MAVLink(
        None, srcSystem=draw(st.integers(0, 255)), srcComponent=draw(st.integers(0, 255))
    )
    mav.seq = draw(st.integers(0, 255))
    v1 = cls.id < 256 and draw(st.booleans())
    if not v1 and draw(st.booleans()):
        mav.signing.secret_key = bytes(32)
        mav.signing.link_id = draw(st.integers(0, 255))
        mav.signing.timestamp = draw(st.integers(1, 1 << 40))
        mav.signing.sign_outgoing = True
    values = draw(field_values(cls))
    return bytes(cls(*values).pack(mav, force_mavlink1=v1))


@st.composite
def raw_frames(draw: st.DrawFn) -> bytes:
    """A frame around random payload bytes of any length 0..255: full, without extensions,
    cut inside a field, zero tail dropped or not, longer than the message."""
    cls = BY_NAME[draw(st.sampled_from(CHOSEN))]
    full = cls.unpacker.size
    length = draw(st.sampled_from([full, full // 2, 1, 0]) | st.integers(0, 255))
    payload = draw(st.binary(min_size=length, max_size=length))
    zeros = draw(st.integers(0, length))
    payload = payload[: length - zeros] + bytes(zeros)
    if draw(st.booleans()):
        payload = payload.rstrip(b"\x00") or payload[:1]
    v1 = cls.id < 256 and draw(st.booleans())
    signature = None if v1 or draw(st.booleans()) else draw(st.binary(min_size=13, max_size=13))
    header = (
        draw(st.integers(0, 255)),
        draw(st.integers(0, 255)),
        draw(st.integers(0, 255)),
        draw(st.integers(0, 255)),
    )
    return frame_of(cls.id, payload, v1=v1, signature=signature, header=header)


@st.composite
def damaged(draw: st.DrawFn, frames: st.SearchStrategy[bytes]) -> bytes:
    """A frame, or the same with one byte changed (magic, length, flags, id, payload, CRC,
    signature), cut short or with bytes after it."""
    frame = draw(frames)
    damage = draw(st.sampled_from(["none", "none", "byte", "byte", "crc", "len", "cut", "tail"]))
    if damage == "byte":
        at = draw(st.integers(0, len(frame) - 1))
        frame = frame[:at] + bytes([frame[at] ^ draw(st.integers(1, 255))]) + frame[at + 1 :]
    elif damage == "crc":
        at = len(frame) - (15 if frame[0] == 0xFD and frame[2] & 1 else 2) + draw(st.integers(0, 1))
        frame = frame[:at] + bytes([frame[at] ^ draw(st.integers(1, 255))]) + frame[at + 1 :]
    elif damage == "len":
        frame = frame[:1] + bytes([draw(st.integers(0, 255))]) + frame[2:]
    elif damage == "cut":
        frame = frame[: draw(st.integers(0, len(frame) - 1))]
    elif damage == "tail":
        frame += draw(st.binary(min_size=1, max_size=20))
    return frame


@settings(max_examples=fuzz_examples(400), deadline=None)
@given(damaged(packed_frames()))
def test_frames_pymavlink_packs_decode_to_the_same_fields(frame: bytes) -> None:
    check_agreement(default_decoder(), frame)


@settings(max_examples=fuzz_examples(400), deadline=None)
@given(damaged(raw_frames()))
def test_frames_of_any_payload_bytes_decode_to_the_same_fields(frame: bytes) -> None:
    check_agreement(default_decoder(), frame)


def sweep_frames(cls: Any, rng: random.Random) -> Iterator[bytes]:
    """For one message: full, without extensions, cut inside, MAVLink 1, signed, bad CRC."""
    full = rng.randbytes(cls.unpacker.size)
    mid = max(1, cls.unpacker.size // 3)
    yield frame_of(cls.id, full)
    yield frame_of(cls.id, full[:mid])
    yield frame_of(cls.id, full[:mid] + bytes(cls.unpacker.size - mid))
    yield frame_of(cls.id, full, signature=rng.randbytes(13))
    yield frame_of(cls.id, full, crc_extra=cls.crc_extra ^ 1)
    if cls.id < 256:
        yield frame_of(cls.id, full, v1=True)
        yield frame_of(cls.id, full[:mid], v1=True)


def test_every_chosen_message_in_every_shape_decodes_as_pymavlink_does() -> None:
    """Deterministic floor under the properties: no message of ours is left to chance."""
    decoder = default_decoder()
    rng = random.Random(2024)
    outcomes: dict[str, set[str]] = {}
    for name in CHOSEN:
        for frame in sweep_frames(BY_NAME[name], rng):
            outcomes.setdefault(name, set()).add(check_agreement(decoder, frame))
    assert all(seen == {"both took", "both refused"} for seen in outcomes.values()), outcomes


def zero_value(kind: str, length: int) -> Any:
    """The value pymavlink packs as zero bytes for a field of ``kind``."""
    if kind == "char":
        return b""
    one: Any = 0.0 if kind in ("float", "double") else 0
    return [one] * length if length else one


def test_every_decoded_message_with_extensions_and_v2_truncation_as_pymavlink() -> None:
    """Every message the decoder holds (not a list typed here), on generated frames: pymavlink
    packs it with extensions set, with every extension zero (MAVLink 2 drops them from the
    wire) and with all fields zero (a one-byte payload); and raw payloads end exactly at the
    end of the base fields and at each extension's end. Each decodes field for field as
    pymavlink does."""
    decoder = default_decoder()
    assert set(decoder.messages) == {BY_NAME[name].id for name in GATEWAY_MESSAGES}
    rng = random.Random(7)
    shapes: dict[str, set[str]] = {}
    for msgid, message in decoder.messages.items():
        cls = PYMAVLINK[msgid]
        kinds = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
        lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
        extensions = {f.name for f in message.wire_fields if f.is_extension}
        values = []
        for name in cls.fieldnames:
            kind, length = kinds[name], lengths[name]
            if kind == "char":
                values.append(b"a")
            elif kind in ("float", "double"):
                values.append([1.5] * length if length else 1.5)
            else:
                values.append([1] * length if length else 1)
        no_extensions = [
            zero_value(kinds[n], lengths[n]) if n in extensions else v
            for n, v in zip(cls.fieldnames, values, strict=True)
        ]
        all_zero = [zero_value(kinds[n], lengths[n]) for n in cls.fieldnames]
        mav = apm.MAVLink(None, srcSystem=3, srcComponent=1)
        frames = {
            "full": bytes(cls(*values).pack(mav)),
            "extensions zero": bytes(cls(*no_extensions).pack(mav)),
            "all zero": bytes(cls(*all_zero).pack(mav)),
        }
        # pymavlink's MAVLink 2 truncation is what these frames test: check it happened.
        assert frames["all zero"][1] == 1, message.name
        if extensions:
            assert frames["extensions zero"][1] <= message.base_length, message.name
        payload = rng.randbytes(message.length).replace(b"\x00", b"\x01")
        ends = [message.base_length]
        for f in message.wire_fields:
            if f.is_extension:
                ends.append(ends[-1] + f.wire_length)
        for end in ends:
            frames[f"raw to {end}"] = frame_of(msgid, payload[:end])
        for shape, frame in frames.items():
            assert check_agreement(decoder, frame) == "both took", (message.name, shape)
            shapes.setdefault(message.name, set()).add(shape)
    assert set(shapes) == {m.name for m in decoder.messages.values()}
    with_extensions = [m for m in decoder.messages.values() if any(
        f.is_extension for f in m.wire_fields)]  # fmt: skip
    assert with_extensions, "no message of ours has extensions: the test would prove nothing"


def test_the_generator_is_right_for_every_message_of_the_dialect() -> None:
    """A decoder of all 300-odd messages: each, full, cut and as MAVLink 1, as pymavlink."""
    messages = load_messages(BY_NAME)
    own = {m.name for m in messages if m.source == "fischer_dialect.xml"}
    assert own == {name for name in GATEWAY_MESSAGES if name.startswith("FISCHER_")}
    decoder = FastDecoder(messages, chars_as_bytes=own)
    rng = random.Random(61000)
    took = expected = 0
    for cls in PYMAVLINK.values():
        expected += 4 if cls.id >= 256 else 6
        for frame in sweep_frames(cls, rng):
            took += check_agreement(decoder, frame) == "both took"
    assert took == expected


# -- particular rules ---------------------------------------------------------------------


def test_the_signature_is_outside_the_crc_and_not_checked_here() -> None:
    mav = apm.MAVLink(None, srcSystem=3, srcComponent=1)
    mav.signing.secret_key = bytes(range(32))
    mav.signing.sign_outgoing = True
    frame = bytes(mav.attitude_encode(1, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0).pack(mav))
    assert frame[2] & 1
    forged = frame[:-1] + bytes([frame[-1] ^ 0xFF])
    for candidate in (frame, forged):
        assert check_agreement(default_decoder(), candidate) == "both took"


def test_unknown_incompatibility_flags_are_refused() -> None:
    frame = bytearray(frame_of(30, bytes(28)))
    frame[2] = 0x02
    with pytest.raises(Malformed, match="incompatibility"):
        default_decoder().decode(bytes(frame))
    assert pymavlink_decode(bytes(frame)) is None


def test_frames_not_ours_are_left_to_pymavlink() -> None:
    decoder = default_decoder()
    raw_imu = frame_of(27, bytes(26))  # RAW_IMU: decoded by pymavlink, no handler of ours
    assert decoder.decode(raw_imu) is None
    assert pymavlink_decode(raw_imu) is not None
    unknown = frame_of(30, bytes(28))[:7] + (60_999).to_bytes(3, "little") + bytes(30)
    for frame in (unknown, b"", b"\xfd\x01", b"\x00" * 20):
        assert decoder.decode(frame) is None


def test_extensions_absent_are_zero_and_chars_nul_stripped_bytes() -> None:
    """FISCHER_DETECTION without its extensions (an old sender's), with a short subtype, and
    with its frame_size; pymavlink reads the same."""
    decoder = default_decoder()
    base = struct.pack("<QIiiffHBB", 1, 2, 3, 4, 5.0, 6.0, 7, 1, 80)
    bare = decoder.decode(frame_of(61000, base))
    assert bare is not None
    assert (bare.subtype, bare.frame_size) == (b"", 0)
    assert (bare.lat, bare.sensor, bare.confidence) == (3, 1, 80)
    tagged = decoder.decode(frame_of(61000, base + b"T-72"))
    assert tagged is not None
    assert (tagged.subtype, tagged.frame_size) == (b"T-72", 0)
    sized = frame_of(61000, base + b"T-72".ljust(16, b"\x00") + bytes([3]))
    fast = decoder.decode(sized)
    assert fast is not None
    assert (fast.subtype, fast.frame_size) == (b"T-72", 3)
    (slow,) = apm.MAVLink(None).parse_buffer(sized)
    assert (slow.subtype, slow.frame_size) == (b"T-72", 3)


def test_upstream_chars_are_text_cut_at_the_first_nul_as_pymavlinks_classes_give() -> None:
    decoder = FastDecoder(load_messages(["STATUSTEXT"]))
    for text in (b"PreArm: GPS", b"two\x00parts", b"caf\xc3\xa9", b""):
        frame = frame_of(253, bytes([4]) + text.ljust(50, b"\x00"))
        assert check_agreement(decoder, frame) == "both took"
        msg = decoder.decode(frame)
        assert msg is not None
        assert msg.text == text.split(b"\x00")[0].decode("ascii", "replace")


def test_arrays_are_lists_and_a_message_is_immutable() -> None:
    decoder = default_decoder()
    msg = decoder.decode(frame_of(285, struct.pack("<I4f", 9, 1.0, 0.0, 0.0, 0.0) + bytes(3)))
    assert msg is not None
    assert msg.get_type() == "GIMBAL_DEVICE_ATTITUDE_STATUS"
    assert msg.q == [1.0, 0.0, 0.0, 0.0]
    with pytest.raises(AttributeError):
        msg.q = [0.0]
    assert "time_boot_ms: 9" in repr(msg)


def test_a_payload_decodes_without_its_frame() -> None:
    msg = default_decoder().decode_payload(33, struct.pack("<IiiiihhhH", 1, 2, 3, 4, 5, 6, 7, 8, 9))
    assert msg is not None
    assert (msg.time_boot_ms, msg.lat, msg.lon, msg.hdg) == (1, 2, 3, 9)
    assert default_decoder().decode_payload(27, b"") is None


# -- the shared corpus ---------------------------------------------------------------------


@pytest.mark.corpus
def test_every_frame_of_every_corpus_tlog_decodes_as_pymavlink_does() -> None:
    """Real logs: MAVLink 1 and 2 mixed, a signed frame, corrupt frames, unknown ids."""
    from gateway.fleet.tlog import read_tlog

    if not CORPUS.is_dir():
        pytest.skip(f"shared corpus absent: {CORPUS}")
    decoder = default_decoder()
    parser = MavlinkParser()
    outcomes: dict[str, int] = {}
    versions: set[int] = set()
    for path in sorted(CORPUS.glob("*.tlog")):
        for record in read_tlog(path):
            frame = record.frame
            counts = (parser.bad, parser.unknown, parser.truncated)
            try:
                taken = parser.feed(frame, whole=True)
            except Malformed:
                taken = []
            clean = counts == (parser.bad, parser.unknown, parser.truncated)
            reference = taken[0] if len(taken) == 1 and clean else None
            try:
                fast = decoder.decode(frame)
            except Malformed:
                assert reference is None, (path.name, reference)
                outcome = "both refused"
            else:
                if fast is None:
                    assert reference is None or reference.get_msgId() not in decoder
                    outcome = "deferred"
                else:
                    assert reference is not None, (path.name, fast)
                    assert_same_message(fast, reference)
                    versions.add(frame[0])
                    outcome = "both took"
            outcomes[outcome] = outcomes.get(outcome, 0) + 1
    assert outcomes["both took"] > 50_000, outcomes
    assert versions == {0xFD, 0xFE}
    assert outcomes.get("both refused", 0) > 0


def test_the_fast_path_is_several_times_pymavlinks_parse_in_cpu_time() -> None:
    """The ratio bench/decode.py measures (about 5.6 here), guarded loosely: CPU time in one
    process, interleaved, median of 3, on the telemetry mix bench/ingest.py sends."""
    sims = [SimulatedAirframe(i + 1, SimProfile(gps_hz=0.0001)) for i in range(4)]
    frames = [f for step in range(250) for sim in sims for f in sim.frames_at(step * 0.05)]
    decoder = default_decoder()
    assert all(decoder.decode(f) is not None for f in frames)

    def cpu(run: Any) -> float:
        start = time.process_time()
        run()
        return time.process_time() - start

    def theirs() -> None:
        parser = apm.MAVLink(None)
        parser.robust_parsing = True
        for frame in frames:
            parser.parse_buffer(frame)

    def ours() -> None:
        for frame in frames:
            decoder.decode(frame)

    ratios = sorted(cpu(theirs) / cpu(ours) for _ in range(3))
    assert ratios[1] > 3.0, ratios


def test_float_comparison_is_bitwise() -> None:
    """The helper the properties rest on: NaN equals only the same NaN, -0.0 is not 0.0."""
    nan = float("nan")
    assert same(nan, nan)
    assert not same(-0.0, 0.0)
    assert not same(1, 1.0)
    assert same([1.0, nan], [1.0, nan])
    assert math.isnan(struct.unpack("<f", b"\x01\x00\xc0\x7f")[0])
