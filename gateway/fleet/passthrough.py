"""A plain local MAVLink endpoint per airframe, for QGroundControl, MAVProxy or MAVSDK.

Frames the gateway accepted from the airframe (authenticated, de-duplicated) are copied to
the local endpoint; what a ground station sends there goes to the airframe on its active
link, sealed by the gateway if that link is tunnelled. The endpoint is plain MAVLink and so
belongs on loopback.

Any local process can reach it, so what only the gateway may say is refused there: a
FISCHER_HOP_SCHEDULE would replace the plan the gateway checked (range, bandwidth, a dwell
that beats the jammer) and uploads. A datagram is refused if the airframe's parser could
find such a frame in it, whole, behind other bytes, or completing bytes forwarded before it
(a stream link joins datagrams), whatever its CRC (a signed link recomputes it); it is
counted (``uplink_refused``) and logged at most every 10 s.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable

import anyio
import anyio.abc
import structlog
from anyio.streams.memory import MemoryObjectSendStream

from gateway.config import Endpoint, LinkConfig
from gateway.errors import LinkError
from gateway.fleet.hopdialect import MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE
from gateway.fleet.links import UdpLink
from gateway.ops.logsetup import RateLimit

__all__ = ["Passthrough"]

log = structlog.get_logger(__name__)

_UPLINK_QUEUE = 256
#: Ground stations the passthrough answers at once (the most recent senders).
MAX_GCS_PEERS = 4
#: Messages only the gateway sends to an airframe.
GATEWAY_ONLY = frozenset({MAVLINK_MSG_ID_FISCHER_HOP_SCHEDULE})
_STX_V2 = 0xFD
#: Forwarded bytes kept to look for a frame that a datagram would complete: a frame less one.
_TAIL_BYTES = 10 + 255 + 2 - 1


def gateway_only_frame(data: bytes, start: int = 0) -> int | None:
    """The id of a message only the gateway sends, if ``data`` holds a MAVLink 2 frame of it
    that ends after ``start``: at any offset (a parser resynchronises) and whatever its CRC
    (a signed link recomputes the CRC of what it signs)."""
    at = data.find(_STX_V2)
    while at != -1 and at + 12 <= len(data):
        msgid = data[at + 7] | data[at + 8] << 8 | data[at + 9] << 16
        end = at + 10 + data[at + 1] + 2
        if msgid in GATEWAY_ONLY and start < end <= len(data):
            return msgid
        at = data.find(_STX_V2, at + 1)
    return None


class Passthrough:
    """Bridges one airframe to a local plain-MAVLink UDP endpoint."""

    def __init__(
        self,
        airframe: str,
        endpoint: Endpoint,
        send_to_airframe: Callable[[str, bytes], Awaitable[None]],
    ) -> None:
        self.airframe = airframe
        config = LinkConfig(uri=endpoint, security="unsecured", name=f"{airframe}-passthrough")
        self.link = UdpLink(
            config, self._from_gcs, lambda _label, _peer: None, max_learned_peers=MAX_GCS_PEERS
        )
        self._send_to_airframe = send_to_airframe
        self._send: MemoryObjectSendStream[bytes] | None = None
        self.downlink_frames = 0
        self.uplink_frames = 0
        self.uplink_dropped = 0
        self.uplink_refused = 0
        self._tail = b""
        self._log_limit = RateLimit(interval_s=10.0)

    def forward(self, frame: bytes) -> None:
        """Copy one accepted frame from the airframe to the local endpoint (never raises)."""
        if self.link.send_nowait(frame):
            self.downlink_frames += 1

    def _from_gcs(self, _label: str, _peer: object, data: bytes) -> None:
        if self._send is None:
            return
        try:
            self._send.send_nowait(data)
        except (anyio.WouldBlock, anyio.BrokenResourceError, anyio.ClosedResourceError):
            self.uplink_dropped += 1
            if self._log_limit.allow("full"):
                log.warning("passthrough_uplink_dropped", airframe=self.airframe)

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind the local endpoint and forward ground-station traffic until cancelled."""
        send, receive = anyio.create_memory_object_stream[bytes](_UPLINK_QUEUE)
        self._send = send
        async with send, receive, anyio.create_task_group() as tg:
            await tg.start(self.link.run)
            task_status.started()
            async for data in receive:
                msgid = gateway_only_frame(self._tail + data, len(self._tail))
                if msgid is not None:
                    self.uplink_refused += 1
                    if self._log_limit.allow("refused"):
                        log.warning(
                            "passthrough_uplink_refused",
                            airframe=self.airframe,
                            msgid=msgid,
                            reason="only the gateway sends this message",
                        )
                    continue
                try:
                    await self._send_to_airframe(self.airframe, data)
                except LinkError as exc:
                    self.uplink_dropped += 1
                    if self._log_limit.allow("link"):
                        log.warning(
                            "passthrough_uplink_failed", airframe=self.airframe, error=str(exc)
                        )
                else:
                    self.uplink_frames += 1
                    self._tail = (self._tail + data)[-_TAIL_BYTES:]

    def status(self) -> dict[str, object]:
        """Counters for /status."""
        return {
            "airframe": self.airframe,
            "uri": str(self.link.endpoint),
            "downlink_frames": self.downlink_frames,
            "uplink_frames": self.uplink_frames,
            "uplink_dropped": self.uplink_dropped,
            "uplink_refused": self.uplink_refused,
        }
