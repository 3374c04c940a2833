"""KLV metadata in an MPEG-2 transport stream: the asynchronous KLV stream of MISB ST 1402.

``KlvTsMuxer`` writes a transport stream of one program with one elementary stream: PMT
``stream_type`` 0x06 (PES private data) with a registration descriptor ``KLVA``, each KLV
packet in one PES packet (``stream_id`` 0xBD, private_stream_1) with a PTS on the 90 kHz
clock, and a PCR on the same PID. PAT and PMT are repeated every ``psi_every`` PES packets.
This is the form both free toolchains read (ffmpeg 5.1, GStreamer 1.22: the spec digest
§8); ffmpeg copies it beside a video stream (``docs/klv.md``). Synchronous carriage
(stream_type 0x15 with metadata AU cells) is not written: ffmpeg and GStreamer mishandle it.
"""

from __future__ import annotations

from datetime import datetime

__all__ = ["KLV_PID", "PMT_PID", "TS_PACKET_BYTES", "KlvTsMuxer", "crc32_mpeg2", "pts_90khz"]

TS_PACKET_BYTES = 188
PMT_PID = 0x1000
KLV_PID = 0x0100
_PROGRAM = 1
_PTS_WRAP = 1 << 33
#: The PCR runs this far (in 90 kHz ticks) ahead of nothing: it is set a little before the PTS
#: so a decoder's clock has reached the packet's time when the packet arrives.
_PCR_LEAD = 9_000


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) if crc & 0x80000000 else crc << 1
        table.append(crc & 0xFFFFFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc32_mpeg2(data: bytes) -> int:
    """CRC-32/MPEG-2 (polynomial 0x04C11DB7, no reflection, initial 0xFFFFFFFF)."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc = ((crc << 8) & 0xFFFFFFFF) ^ _CRC_TABLE[((crc >> 24) ^ byte) & 0xFF]
    return crc


def pts_90khz(time: datetime) -> int:
    """A presentation time on the 90 kHz clock from an aware time (wraps at 2^33)."""
    return (round(time.timestamp() * 1_000_000) * 9 // 100) % _PTS_WRAP


def _section(table_id: int, table_id_ext: int, body: bytes) -> bytes:
    length = 5 + len(body) + 4  # the header after section_length, the body, the CRC
    head = bytes((table_id, 0xB0 | (length >> 8), length & 0xFF))
    head += table_id_ext.to_bytes(2, "big") + bytes((0xC1, 0x00, 0x00))
    section = head + body
    return section + crc32_mpeg2(section).to_bytes(4, "big")


def _timestamp(prefix: int, ticks: int) -> bytes:
    ticks %= _PTS_WRAP
    return bytes((
        (prefix << 4) | ((ticks >> 29) & 0x0E) | 1,
        (ticks >> 22) & 0xFF,
        ((ticks >> 14) & 0xFE) | 1,
        (ticks >> 7) & 0xFF,
        ((ticks << 1) & 0xFE) | 1,
    ))  # fmt: skip


def _pcr(ticks: int) -> bytes:
    base = ticks % _PTS_WRAP
    return (base << 15 | 0x7E << 9).to_bytes(6, "big")  # base, 6 reserved bits, extension 0


class KlvTsMuxer:
    """Turns KLV packets with their times into 188-byte transport stream packets."""

    def __init__(self, *, pid: int = KLV_PID, pmt_pid: int = PMT_PID, psi_every: int = 10):
        self.pid = pid
        self.pmt_pid = pmt_pid
        self.psi_every = psi_every
        self._continuity: dict[int, int] = {}
        self._since_psi = psi_every  # PSI first

    def _ts(self, pid: int, payload: bytes, *, start: bool, adaptation: bytes = b"") -> bytes:
        counter = self._continuity.get(pid, 0)
        self._continuity[pid] = (counter + 1) & 0x0F
        room = TS_PACKET_BYTES - 4
        need_af = bool(adaptation) or len(payload) < room
        header = bytes((
            0x47,
            (0x40 if start else 0) | (pid >> 8),
            pid & 0xFF,
            (0x30 if need_af else 0x10) | counter,
        ))  # fmt: skip
        if not need_af:
            return header + payload
        # Adaptation field: its length byte, then flags and fields, then 0xFF stuffing.
        stuffing = room - len(payload) - 1 - len(adaptation)
        if adaptation:
            field = adaptation + b"\xff" * stuffing
        elif stuffing > 0:
            field = b"\x00" + b"\xff" * (stuffing - 1)
        else:
            field = b""
        return header + bytes((len(field),)) + field + payload

    def psi(self) -> bytes:
        """A PAT and a PMT (two TS packets)."""
        pat = _section(
            0x00, 1, _PROGRAM.to_bytes(2, "big") + (0xE000 | self.pmt_pid).to_bytes(2, "big")
        )
        registration = b"\x05\x04KLVA"
        es = bytes((0x06,)) + (0xE000 | self.pid).to_bytes(2, "big")
        es += (0xF000 | len(registration)).to_bytes(2, "big") + registration
        pmt_body = (0xE000 | self.pid).to_bytes(2, "big") + b"\xf0\x00" + es
        pmt = _section(0x02, _PROGRAM, pmt_body)
        out = b""
        for pid, section in ((0, pat), (self.pmt_pid, pmt)):
            payload = b"\x00" + section
            out += self._ts(
                pid, payload + b"\xff" * (TS_PACKET_BYTES - 4 - len(payload)), start=True
            )
        return out

    def mux(self, klv: bytes, pts: int) -> bytes:
        """The TS packets carrying one KLV packet presented at ``pts`` (90 kHz ticks).

        PAT and PMT come first when due. Raises ``ValueError`` for a KLV packet too long
        for one PES packet (65,526 bytes).
        """
        header = b"\x80\x80\x05" + _timestamp(0x2, pts)
        if len(header) + len(klv) > 0xFFFF:
            raise ValueError(f"a KLV packet of {len(klv)} bytes does not fit one PES packet")
        pes = b"\x00\x00\x01\xbd" + (len(header) + len(klv)).to_bytes(2, "big") + header + klv
        out = bytearray()
        if self._since_psi >= self.psi_every:
            out += self.psi()
            self._since_psi = 0
        self._since_psi += 1
        first_af = b"\x50" + _pcr(pts - _PCR_LEAD)  # random access, PCR
        room = TS_PACKET_BYTES - 4 - 1 - len(first_af)
        out += self._ts(self.pid, pes[:room], start=True, adaptation=first_af)
        for at in range(room, len(pes), TS_PACKET_BYTES - 4):
            out += self._ts(self.pid, pes[at : at + TS_PACKET_BYTES - 4], start=False)
        return bytes(out)
