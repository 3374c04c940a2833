"""Detections held before they are acknowledged: the gateway's half of FISCHER_DETECTION_ACK.

An airframe keeps each detection until the gateway acknowledges it (docs/detection-ack.md).
The gateway acknowledges a detection only once it is committed to the spool:

1. the first detection of a datagram joins the spool's open group commit (one transaction for
   the loop pass, shared with the bus's appends and the sinks' confirmations; opened now if
   there is none: ``DetectionLedger.group``);
2. a detection id already in the ledger is a re-send whose acknowledgement was lost: it is
   acknowledged again as DUPLICATE and not published;
3. otherwise it is published; if the bus held it (spooled for every sink it goes to), its id
   is remembered in the same transaction and a HELD acknowledgement is due; if not (spool
   full) nothing is due, and the airframe sends it again later;
4. when the datagram is done its due acknowledgements wait for the group to end: once it has
   committed (at the end of the loop pass, or at once where no loop commits it) they are
   queued for sending (``run`` sends them, batched per airframe); if it rolled back, none is.

Who opened the group, and in which order the bus, the sinks and the intake write into it,
does not matter: the spool owns it.

A lost acknowledgement costs a re-send, never a detection; an unsent one is counted.
"""

from __future__ import annotations

import asyncio
import functools
from collections import deque
from collections.abc import Callable
from typing import Protocol

import structlog

from gateway.errors import FrameError, LinkError
from gateway.events import Detection, Event
from gateway.fleet.session import AirframeSession
from gateway.ops.instruments import Instruments
from gateway.ops.logsetup import RateLimit

__all__ = ["ACK_DUPLICATE", "ACK_HELD", "DetectionAcks", "DetectionLedger"]

log = structlog.get_logger(__name__)

#: FISCHER_DETECTION_ACK_RESULT values.
ACK_HELD = 0
ACK_DUPLICATE = 1
_RESULT_NAMES = {ACK_HELD: "held", ACK_DUPLICATE: "duplicate"}
#: Acknowledgements waiting to be sent at most; past it the oldest go (the airframe re-sends).
ACK_QUEUE_MAX = 10_000
#: Acknowledgements of one airframe are sent together up to about this many bytes.
ACK_SEND_BYTES = 1024


class Commit(Protocol):
    """The spool's open group of writes (``gateway.spool.group.Commit``), as the intake sees it."""

    @property
    def scheduled(self) -> bool:
        """True if the end of the loop pass commits it."""
        ...

    def when_done(self, callback: Callable[[bool], None]) -> None:
        """Call ``callback(committed)`` when the group ends."""
        ...


class DetectionLedger(Protocol):
    """What the intake needs of the spool: its group commit and the detection ids taken in."""

    def group(self) -> Commit:
        """The open group commit (opened now if none is); raises if the spool cannot begin."""
        ...

    def flush(self) -> bool:
        """Commit the open group now; False if it did not commit."""
        ...

    def seen(self, event_id: str) -> bool:
        """True if this detection was taken in already."""
        ...

    def remember(self, event_id: str) -> None:
        """Record this detection as taken in."""
        ...


class DetectionAcks:
    """Takes detections into the spool and acknowledges them once committed."""

    def __init__(
        self, publish: Callable[[Event], bool], ledger: DetectionLedger, instruments: Instruments
    ) -> None:
        self._publish = publish
        self._ledger = ledger
        self._inst = instruments
        self._group: Commit | None = None
        self._due: list[tuple[AirframeSession, int, int, int]] = []
        self._queue: deque[tuple[AirframeSession, bytes]] = deque(maxlen=ACK_QUEUE_MAX)
        # asyncio's own event, set and cleared: no anyio back-end look-up per datagram.
        self._ready = asyncio.Event()
        self._log = RateLimit(interval_s=10.0)

    @property
    def is_open(self) -> bool:
        """True while a datagram's detections are taken and their acknowledgements not settled."""
        return self._group is not None

    def take(
        self,
        airframe: AirframeSession,
        label: str,
        detection: Detection,
        detection_id: int,
        time_usec: int,
    ) -> None:
        """Take one detection of the datagram being read (see the module docstring)."""
        if self._group is None:
            # Raises if the spool cannot begin: nothing taken, nothing acked.
            self._group = self._ledger.group()
        if self._ledger.seen(detection.event_id):
            self._inst.link_ignored.labels(label, "duplicate_detection").inc()
            self._due.append((airframe, detection_id, time_usec, ACK_DUPLICATE))
            return
        if self._publish(detection):
            self._ledger.remember(detection.event_id)
            self._due.append((airframe, detection_id, time_usec, ACK_HELD))

    def commit(self) -> None:
        """The datagram is done: its acknowledgements are queued once its group has committed."""
        group, self._group = self._group, None
        due, self._due = self._due, []
        if group is None:
            return
        group.when_done(functools.partial(self._settled, due))
        if not group.scheduled:
            self._ledger.flush()  # no loop pass to end it: now

    def _settled(self, due: list[tuple[AirframeSession, int, int, int]], committed: bool) -> None:
        if not committed:
            # Not committed: nothing is acknowledged, the airframes send these again.
            if due and self._log.allow("commit"):
                log.error("detections_not_committed", count=len(due))
            return
        for airframe, detection_id, time_usec, result in due:
            frame = airframe.encode_detection_ack(detection_id, time_usec, result)
            self._queue.append((airframe, frame))
            self._inst.detections_acked.labels(airframe.id, _RESULT_NAMES[result]).inc()
        if due:
            self._ready.set()

    async def run(self) -> None:
        """Send queued acknowledgements, those of one airframe together, until cancelled."""
        while True:
            await self._ready.wait()
            self._ready.clear()
            pending: dict[str, tuple[AirframeSession, bytearray]] = {}
            while self._queue:
                airframe, frame = self._queue.popleft()
                _, frames = pending.setdefault(airframe.id, (airframe, bytearray()))
                frames += frame
                if len(frames) >= ACK_SEND_BYTES:
                    await self._send(airframe, bytes(frames))
                    frames.clear()
            for airframe, frames in pending.values():
                if frames:
                    await self._send(airframe, bytes(frames))

    async def _send(self, airframe: AirframeSession, frames: bytes) -> None:
        try:
            await airframe.send(frames)
        except (LinkError, FrameError):
            # The airframe sends the detection again and is acknowledged DUPLICATE then.
            self._inst.link_ignored.labels(airframe.id, "ack_unsent").inc()
