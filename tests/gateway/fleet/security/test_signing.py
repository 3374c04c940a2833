"""MAVLink 2 signing: frames signed by pymavlink verify; forgeries and replays do not."""

from __future__ import annotations

import hashlib
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.errors import AuthenticationFailed, FrameError, Replayed
from gateway.fleet.security.signing import SigningVerifier, mavlink_timestamp_now, sign_frame
from gateway.testing import fuzz_examples

KEY = hashlib.sha256(b"fischer-test-passphrase").digest()


def signer(key: bytes = KEY, link_id: int = 3, ts: int | None = None) -> mav.MAVLink:
    m = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    m.signing.secret_key = key
    m.signing.link_id = link_id
    m.signing.sign_outgoing = True
    m.signing.timestamp = mavlink_timestamp_now(time.time()) if ts is None else ts
    return m


def heartbeat(m: mav.MAVLink) -> bytes:
    return bytes(m.heartbeat_encode(1, 3, 0, 0, 4).pack(m))


def verifier(require: bool = True) -> SigningVerifier:
    return SigningVerifier(KEY, require_signed=require, clock=time.time)


def test_the_spec_digest_example_verifies() -> None:
    frame = bytes.fromhex("fd0901000007010000000000000001030004033d9b0378563412000023958ef297af")
    v = SigningVerifier(KEY, require_signed=True, clock=lambda: 1420070400 + 0x12345678 / 1e5)
    assert v.verify(frame) is True


def test_pymavlink_signed_frames_are_accepted() -> None:
    v, m = verifier(), signer()
    assert all(v.verify(heartbeat(m)) for _ in range(10))
    assert v.counters.signed == 10


def test_wrong_key_is_rejected() -> None:
    v = verifier()
    with pytest.raises(AuthenticationFailed, match="signature"):
        v.verify(heartbeat(signer(key=bytes(32))))
    assert v.counters.bad_signature == 1


def test_unsigned_rejected_when_required_accepted_in_lab_mode() -> None:
    plain = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    frame = heartbeat(plain)
    with pytest.raises(AuthenticationFailed, match="unsigned"):
        verifier(require=True).verify(frame)
    assert verifier(require=False).verify(frame) is False


def test_replayed_frame_is_rejected() -> None:
    v, m = verifier(), signer()
    frame = heartbeat(m)
    v.verify(frame)
    with pytest.raises(Replayed):
        v.verify(frame)


def test_forged_huge_timestamp_does_not_lock_out_genuine_frames() -> None:
    """The pymavlink pitfall: a forged frame must not advance the stream's timestamp."""
    v, genuine = verifier(), signer()
    v.verify(heartbeat(genuine))
    forger = signer(key=bytes(32), ts=2**47)
    with pytest.raises(AuthenticationFailed):
        v.verify(heartbeat(forger))
    assert v.verify(heartbeat(genuine)) is True


def test_new_stream_from_the_distant_past_is_rejected() -> None:
    old = signer(ts=mavlink_timestamp_now(time.time() - 3600))
    with pytest.raises(Replayed, match="minute"):
        verifier().verify(heartbeat(old))


def test_our_signer_matches_pymavlink() -> None:
    m = signer(ts=1000)
    frame = heartbeat(m)
    unsigned = frame[:-13]
    assert sign_frame(unsigned, KEY, 3, 1000) == frame


@settings(max_examples=fuzz_examples(300), deadline=None)
@given(st.binary(max_size=300))
def test_arbitrary_bytes_raise_only_frame_errors(blob: bytes) -> None:
    v = verifier()
    try:
        v.verify(b"\xfd" + blob)
    except FrameError:
        pass
    else:
        assert v.counters.signed == 1


def test_frames_signed_before_the_verifier_started_are_replays() -> None:
    """Replay state is in memory: a capture from before a restart must not pass after it."""
    captured = heartbeat(signer())
    time.sleep(0.001)
    v = verifier()
    with pytest.raises(Replayed, match="before the gateway started"):
        v.verify(captured)
    assert v.counters.replayed == 1
    assert v.verify(heartbeat(signer())) is True


def test_outbound_signer_output_verifies_in_pymavlink() -> None:
    """What the gateway signs for a signed link, pymavlink's own signing check accepts."""
    from gateway.fleet.mavlink import crc_extra
    from gateway.fleet.security.signing import OutboundSigner

    plain = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    command = bytes(plain.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(plain))
    out = OutboundSigner(KEY, crc_extra=crc_extra, clock=time.time, link_id=7)
    signed = [out.sign(command) for _ in range(3)]
    receiver = mav.MAVLink(None)
    receiver.signing.secret_key = KEY
    receiver.signing.sign_outgoing = False
    for frame in signed:
        msg = receiver.parse_char(frame)
        assert msg is not None
        assert msg.get_type() == "COMMAND_LONG"
        assert msg.get_signed()
        assert msg.get_link_id() == 7
        assert msg.command == 400
    assert receiver.signing.badsig_count == 0
    stamps = [int.from_bytes(f[-12:-6], "little") for f in signed]
    assert stamps == sorted(set(stamps))
