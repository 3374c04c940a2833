"""A plain local MAVLink endpoint per airframe, for QGroundControl, MAVProxy or MAVSDK.

Frames the gateway accepted from the airframe (authenticated, de-duplicated) are copied to
the local endpoint; what a ground station sends there goes to the airframe on its active
link, sealed by the gateway if that link is tunnelled. The endpoint is plain MAVLink and so
belongs on loopback.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable

import anyio
import anyio.abc
import structlog
from anyio.streams.memory import MemoryObjectSendStream

from gateway.config import Endpoint, LinkConfig
from gateway.errors import LinkError
from gateway.fleet.links import UdpLink
from gateway.ops.logsetup import RateLimit

__all__ = ["Passthrough"]

log = structlog.get_logger(__name__)

_UPLINK_QUEUE = 256
#: Ground stations the passthrough answers at once (the most recent senders).
MAX_GCS_PEERS = 4


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

    def status(self) -> dict[str, object]:
        """Counters for /status."""
        return {
            "airframe": self.airframe,
            "uri": str(self.link.endpoint),
            "downlink_frames": self.downlink_frames,
            "uplink_frames": self.uplink_frames,
            "uplink_dropped": self.uplink_dropped,
        }
