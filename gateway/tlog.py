"""Recorded MAVLink logs (.tlog, as MAVProxy, QGroundControl and Mission Planner write them).

Each record is an 8-byte big-endian UNIX timestamp in microseconds followed by one raw
MAVLink frame (MAVLink 1: 0xFE, 8 + LEN bytes; MAVLink 2: 0xFD, 12 + LEN bytes, + 13 if
signed). ``read_tlog`` streams records with bounded memory and resynchronises after damage;
``replay_udp`` sends them to a gateway as an airframe would.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

import anyio
import anyio.abc
import anyio.lowlevel

__all__ = ["TlogRecord", "TlogStats", "parse_udp_target", "read_tlog", "replay_udp"]

_TS = struct.Struct(">Q")
_DAY_US = 86_400 * 1_000_000
_CHUNK = 1 << 16


@dataclass(frozen=True, slots=True)
class TlogRecord:
    """One record: when it was logged and the raw frame."""

    timestamp_us: int
    frame: bytes


@dataclass(slots=True)
class TlogStats:
    """What ``read_tlog`` saw: records yielded and bytes skipped to resynchronise."""

    records: int = 0
    skipped_bytes: int = 0


def _frame_length(buf: bytes | bytearray, pos: int) -> int | None:
    """Length of the frame starting at ``pos``, or None if no frame can start there."""
    if pos + 3 > len(buf):
        return None
    magic = buf[pos]
    if magic == 0xFE:
        return 8 + buf[pos + 1]
    if magic == 0xFD:
        return 12 + buf[pos + 1] + (13 if buf[pos + 2] & 0x01 else 0)
    return None


def read_tlog(path: Path, stats: TlogStats | None = None) -> Iterator[TlogRecord]:
    """Yield the records of ``path``; never raises on damaged content (only on I/O errors).

    After a record that does not start with a MAVLink magic byte, it scans forward for the
    next position where a timestamp within a day of the last good one is followed by a
    magic byte. A truncated last record is dropped.
    """
    stats = stats if stats is not None else TlogStats()
    buf = bytearray()
    pos = 0
    last_ts: int | None = None
    eof = False
    with path.open("rb") as handle:
        while True:
            if not eof and len(buf) - pos < 8 + 280:
                del buf[:pos]
                pos = 0
                chunk = handle.read(_CHUNK)
                eof = not chunk
                buf += chunk
            if len(buf) - pos < 9:
                return
            (ts,) = _TS.unpack_from(buf, pos)
            plausible = last_ts is None or abs(ts - last_ts) <= _DAY_US
            length = _frame_length(buf, pos + 8) if plausible else None
            if length is None:
                pos += 1
                stats.skipped_bytes += 1
                continue
            end = pos + 8 + length
            if end > len(buf):
                if eof:
                    return
                continue
            last_ts = ts
            stats.records += 1
            yield TlogRecord(ts, bytes(buf[pos + 8 : end]))
            pos = end


def parse_udp_target(text: str) -> tuple[str, int]:
    """``udp://HOST:PORT`` → (host, port); raise ``ValueError`` naming ``text`` otherwise."""
    parts = urlsplit(text)
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme != "udp" or not parts.hostname or not port:
        raise ValueError(f"expected udp://HOST:PORT, found {text!r}")
    return parts.hostname, port


async def replay_udp(
    path: Path,
    host: str,
    port: int,
    *,
    speed: float | None = 1.0,
    seal: Callable[[bytes], bytes] | None = None,
    task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
) -> int:
    """Send each frame of ``path`` as one datagram; return how many were sent.

    ``speed`` scales the recorded pacing (2.0 is twice as fast); None sends as fast as the
    socket takes them. ``seal``, when given, wraps each frame (the tunnel's ``Sealer.seal``).
    """
    if speed is not None and speed <= 0:
        raise ValueError(f"speed must be positive, found {speed}")
    sent = 0
    async with await anyio.create_connected_udp_socket(remote_host=host, remote_port=port) as sock:
        task_status.started()
        start_mono = anyio.current_time()
        first_ts: int | None = None
        for record in read_tlog(path):
            if speed is not None:
                first_ts = record.timestamp_us if first_ts is None else first_ts
                due = start_mono + (record.timestamp_us - first_ts) / 1e6 / speed
                delay = due - anyio.current_time()
                if delay > 0:
                    await anyio.sleep(delay)
            elif sent % 64 == 0:
                # Let the receiver (often in this process) keep up.
                await anyio.lowlevel.checkpoint()
            await sock.send(seal(record.frame) if seal else record.frame)
            sent += 1
    return sent
