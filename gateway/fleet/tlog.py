"""Recorded MAVLink logs (.tlog, as MAVProxy, QGroundControl and Mission Planner write them).

Each record is an 8-byte big-endian UNIX timestamp in microseconds followed by one raw
MAVLink frame (MAVLink 1: 0xFE, 8 + LEN bytes; MAVLink 2: 0xFD, 12 + LEN bytes, + 13 if
signed). ``read_tlog`` streams records with bounded memory and resynchronises after damage;
``replay_udp`` sends them to a gateway as an airframe would.
"""

from __future__ import annotations

import math
import socket
import struct
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from itertools import islice
from pathlib import Path
from urllib.parse import urlsplit

import anyio
import anyio.abc
import anyio.lowlevel
import anyio.to_thread
import structlog

__all__ = [
    "ReplayStats",
    "TlogRecord",
    "TlogStats",
    "parse_udp_target",
    "read_tlog",
    "replay_udp",
]

log = structlog.get_logger(__name__)

_TS = struct.Struct(">Q")
_DAY_US = 86_400 * 1_000_000
_EPOCH_US = (946_684_800 * 1_000_000, 4_102_444_800 * 1_000_000)  # 2000-01-01 .. 2100-01-01
_MAX_RECORD = 8 + 280  # timestamp + the largest frame (signed MAVLink 2, 255-byte payload)
_LOOKAHEAD = 3 * _MAX_RECORD + 11  # three records and the header of a fourth
_CHUNK = 1 << 16
_BATCH = 256  # records read per worker-thread call in replay_udp


@dataclass(frozen=True, slots=True)
class TlogRecord:
    """One record: when it was logged (UNIX µs) and the raw MAVLink frame."""

    timestamp_us: int
    frame: bytes


@dataclass(slots=True)
class TlogStats:
    """What ``read_tlog`` saw: records yielded, bytes skipped to resynchronise, tail dropped."""

    records: int = 0
    skipped_bytes: int = 0
    truncated_bytes: int = 0


def _record_end(buf: bytearray, pos: int) -> int | None:
    """End of the record at ``pos`` if a MAVLink magic byte follows its timestamp, else None.

    None also when the frame header is not in ``buf``; the end may lie beyond ``buf``.
    """
    if pos + 11 > len(buf):
        return None
    magic, length = buf[pos + 8], buf[pos + 9]
    if magic == 0xFE:
        return pos + 16 + length
    if magic == 0xFD:
        return pos + 20 + length + (13 if buf[pos + 10] & 0x01 else 0)
    return None


def _lines_up(buf: bytearray, pos: int, count: int, *, eof: bool) -> bool:
    """Whether ``count`` records in a row start at ``pos`` (fewer if the file ends first)."""
    for _ in range(count):
        end = _record_end(buf, pos)
        if end is None:
            return eof and len(buf) - pos < 11
        if end > len(buf):
            return eof
        pos = end
    return True


def read_tlog(path: Path, stats: TlogStats | None = None) -> Generator[TlogRecord, None, None]:
    """Yield the records of ``path`` in order, reading it in chunks (bounded memory).

    Damaged content never raises (only I/O errors do). A record is taken when a magic
    byte follows its timestamp and either its timestamp is within a day of the last good
    one; or it starts the file, or follows the previous record directly with the next
    record lining up too (a clock jump), with a timestamp before 2100; or its timestamp
    is in 2000..2100 and the next two records line up (recovery across a clock jump).
    Otherwise one byte is skipped and counted in ``stats.skipped_bytes``, and the scan goes
    on. A truncated tail is dropped and counted in ``stats.truncated_bytes``. CRCs are not
    checked here: that is the parser's job.
    """
    stats = stats if stats is not None else TlogStats()
    buf = bytearray()
    pos = 0
    last_ts: int | None = None
    in_step = True  # pos is where the previous record ended (or the start of the file)
    eof = False
    with path.open("rb") as handle:
        while True:
            if not eof and len(buf) - pos < _LOOKAHEAD:
                del buf[:pos]
                pos = 0
                chunk = handle.read(_CHUNK)
                eof = not chunk
                buf += chunk
                continue
            end = _record_end(buf, pos)
            if end is None and eof and len(buf) - pos < 11:
                stats.truncated_bytes += len(buf) - pos
                break
            (ts,) = _TS.unpack_from(buf, pos) if end is not None else (0,)
            if end is None or not (
                (last_ts is not None and abs(ts - last_ts) <= _DAY_US)
                or (
                    in_step
                    and ts < _EPOCH_US[1]
                    and (last_ts is None or _lines_up(buf, pos, 2, eof=eof))
                )
                or (_EPOCH_US[0] <= ts < _EPOCH_US[1] and _lines_up(buf, pos, 3, eof=eof))
            ):
                pos += 1
                stats.skipped_bytes += 1
                in_step = False
                continue
            if end > len(buf):  # only at the end of the file: the lookahead covers a record
                stats.truncated_bytes += len(buf) - pos
                break
            last_ts = ts
            stats.records += 1
            yield TlogRecord(ts, bytes(buf[pos + 8 : end]))
            pos, in_step = end, True
    if stats.skipped_bytes:
        log.warning(
            "tlog_damage_skipped",
            path=str(path),
            skipped_bytes=stats.skipped_bytes,
            records=stats.records,
        )


def parse_udp_target(text: str) -> tuple[str, int]:
    """``udp://HOST:PORT`` → ``(host, port)``; ``[::1]`` brackets an IPv6 host.

    Raises ``ValueError`` naming ``text`` when it is anything else (another scheme, no
    host, a port outside 1..65535, a path, query or user part).
    """
    parts = urlsplit(text)
    try:
        port = parts.port
    except ValueError:
        port = None
    extra = parts.path not in ("", "/") or parts.query or parts.fragment or parts.username
    if parts.scheme != "udp" or not parts.hostname or not port or extra:
        raise ValueError(f"expected udp://HOST:PORT, got {text!r}")
    return parts.hostname, port


@dataclass(slots=True)
class ReplayStats:
    """How a replay went: frames sent, sends refused, and how far into the log it got."""

    sent: int = 0
    refused: int = 0
    """Sends the kernel refused because an ICMP port-unreachable came back: nobody listens."""
    log_position_s: float = 0.0
    """Seconds from the log's first record to the last one sent."""


async def replay_udp(
    path: Path,
    host: str,
    port: int,
    *,
    speed: float | None = 1.0,
    seal: Callable[[bytes], bytes] | None = None,
    progress_interval_s: float | None = None,
    stats: ReplayStats | None = None,
    task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
) -> int:
    """Send each frame of ``path`` as one UDP datagram to ``host:port``; return how many.

    ``speed`` scales the recorded pacing on ``anyio.current_time()`` (2.0 is twice as
    fast); None sends as fast as the socket takes them. A gap that goes back in time or
    forward by more than a day (a clock jump) is not waited for. ``seal``, when given,
    wraps each frame (the tunnel's ``Sealer.seal``). ``task_status.started()`` is called
    once the file is open and the socket exists. The file is read in a worker thread.

    The socket is connected, so an ICMP port-unreachable from the target (nothing listens
    there) refuses the next send: that frame is counted in ``stats.refused``, not sent, a
    warning is logged once, and the replay goes on (a listener may come up). Every
    ``progress_interval_s`` a ``replay_progress`` record says how far it got.
    Raises ``ValueError`` for a bad ``speed``, ``OSError`` for the file or the socket.
    """
    if speed is not None and not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"speed: expected a positive finite number or None, got {speed!r}")
    stats = stats if stats is not None else ReplayStats()
    damage = TlogStats()
    records = read_tlog(path, damage)
    try:
        batch = await anyio.to_thread.run_sync(_take, records)
        family, _, _, _, address = (await anyio.getaddrinfo(host, port, type=socket.SOCK_DGRAM))[0]
        with socket.socket(family, socket.SOCK_DGRAM) as sock:
            sock.setblocking(False)
            sock.connect(address)
            task_status.started()
            now = due = anyio.current_time()
            next_progress = None if progress_interval_s is None else now + progress_interval_s
            first_ts = prev_ts = batch[0].timestamp_us if batch else None
            while batch:
                for record in batch:
                    if speed is not None:
                        gap_us = 0 if prev_ts is None else record.timestamp_us - prev_ts
                        due += gap_us / 1e6 / speed if 0 < gap_us <= _DAY_US else 0.0
                        prev_ts = record.timestamp_us
                        await anyio.sleep(max(due - anyio.current_time(), 0.0))
                    else:
                        # A UDP send never yields: without this, a receiver in this process
                        # (tests, the demo) would starve and the kernel would drop datagrams.
                        await anyio.lowlevel.checkpoint()
                    frame = seal(record.frame) if seal else record.frame
                    if await _send(sock, frame):
                        stats.sent += 1
                    else:
                        stats.refused += 1
                        if stats.refused == 1:
                            log.warning(
                                "replay_refused",
                                target=f"udp://{host}:{port}",
                                reason="ICMP port unreachable: nothing listens there",
                            )
                    if first_ts is not None:
                        stats.log_position_s = (record.timestamp_us - first_ts) / 1e6
                    if next_progress is not None and anyio.current_time() >= next_progress:
                        next_progress = anyio.current_time() + (progress_interval_s or 0.0)
                        _log_progress(stats, record.timestamp_us)
                batch = await anyio.to_thread.run_sync(_take, records)
    finally:
        records.close()
    log.debug(
        "tlog_replayed", path=str(path), frames=stats.sent, skipped_bytes=damage.skipped_bytes
    )
    return stats.sent


async def _send(sock: socket.socket, data: bytes) -> bool:
    """Send one datagram; False if the kernel refused it after an ICMP port-unreachable."""
    while True:
        try:
            sock.send(data)
        except BlockingIOError:
            await anyio.wait_writable(sock)
        except ConnectionRefusedError:
            return False
        else:
            return True


def _log_progress(stats: ReplayStats, timestamp_us: int) -> None:
    log_time = datetime.fromtimestamp(timestamp_us / 1e6, UTC).isoformat(timespec="seconds")
    log.info(
        "replay_progress",
        frames_sent=stats.sent,
        refused=stats.refused,
        log_time=log_time,
        log_position_s=round(stats.log_position_s, 1),
    )


def _take(records: Iterator[TlogRecord]) -> list[TlogRecord]:
    return list(islice(records, _BATCH))
