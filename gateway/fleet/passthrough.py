"""A local MAVLink endpoint per airframe, for QGroundControl, MAVProxy or MAVSDK.

Frames the gateway accepted from the airframe (authenticated, de-duplicated) are copied to
the endpoint. What a ground station sends back is uplink, and the gateway authenticates it to
the airframe (sealed in the tunnel or signed with the airframe's key), so nothing goes on
unchecked. Each passthrough states its ``uplink`` mode: ``none`` (telemetry out only),
``signed`` (only frames the ground station signed with its own key, ``key_file``; the
endpoint's downlink is signed with that key too) or ``open`` (any local process).

Whatever the mode, every datagram is parsed into whole MAVLink 2 frames with a good CRC;
everything else (garbage, MAVLink 1, unknown ids, cut frames, bad or replayed signatures) is
dropped and counted, and so is a frame that claims the airframe's own system id (the
airframe's frames go out signed with the station's key: sent back, they would verify). Each
frame then meets the command policy (``uplinkpolicy``), an
allowlist that never lets an effector command through, and only a frame the gateway
re-serialises from its parsed fields goes to the airframe: bytes a ground station sent never
reach it as they were. A refused command or mission item is answered (COMMAND_ACK or
MISSION_ACK ``DENIED``; an upload in progress is cancelled at the airframe) so the ground
station neither retries forever nor stalls. Refusals are counted by reason
(``fg_passthrough_refused_total``) and logged with the sender at most every 10 s per reason.
No datagram, frame or sequence of them ends the daemon.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Awaitable, Callable
from typing import Any

import anyio
import anyio.abc
import structlog
from anyio.streams.memory import MemoryObjectSendStream

from gateway.config import LinkConfig, PassthroughConfig
from gateway.errors import FrameError, GatewayError
from gateway.fleet.links import UdpLink
from gateway.fleet.mavlink import MavlinkParser, crc_extra, dialect
from gateway.fleet.security.signing import OutboundSigner, SigningVerifier
from gateway.fleet.uplinkpolicy import COMMAND_MSGS, MISSION_ITEM_MSGS, Refusal, check
from gateway.ops.logsetup import RateLimit
from gateway.ops.metrics import Counter as MetricCounter

__all__ = ["MAX_DATAGRAM_BYTES", "MAX_GCS_PEERS", "Passthrough"]

log = structlog.get_logger(__name__)

_UPLINK_QUEUE = 256
#: Datagrams from senders that have not proved themselves may fill only this much of the
#: queue: the rest is kept for the ground stations the passthrough answers, so a local
#: flood without the key cannot crowd out a signed station's commands.
_STRANGER_QUEUE = 192
#: Ground stations the passthrough answers at once (the most recent that proved themselves).
MAX_GCS_PEERS = 4
#: A ground station's datagram holds a few frames at most; anything longer is refused.
MAX_DATAGRAM_BYTES = 2048
_STX_V2 = 0xFD
_AUTOPILOT_COMPID = 1

Peer = tuple[str, int]


class Passthrough:
    """Bridges one airframe to a local MAVLink UDP endpoint under the command policy."""

    def __init__(
        self,
        airframe: str,
        sysid: int,
        config: PassthroughConfig,
        send_to_airframe: Callable[[str, bytes], Awaitable[None]],
        *,
        gcs_key: bytes | None = None,
        refused_metric: MetricCounter | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.airframe = airframe
        self.sysid = sysid
        self.config = config
        self.uplink = config.uplink
        link_config = LinkConfig(uri=config.uri, security="unsecured", name=f"{airframe}-gcs")
        self.link = UdpLink(
            link_config,
            self._from_gcs,
            lambda _label, _peer: None,
            max_learned_peers=MAX_GCS_PEERS,
            learn_on_receive=False,
        )
        self._send_to_airframe = send_to_airframe
        self._send: MemoryObjectSendStream[tuple[Peer, bytes]] | None = None
        self._parser = MavlinkParser(max_chunk_bytes=MAX_DATAGRAM_BYTES)
        self._packer = dialect.MAVLink(None)
        self._verifier: SigningVerifier | None = None
        self._signer: OutboundSigner | None = None
        if config.uplink == "signed":
            if gcs_key is None:
                raise ValueError("a signed passthrough needs the ground station's key")
            self._verifier = SigningVerifier(gcs_key, require_signed=True, clock=clock)
            self._signer = OutboundSigner(gcs_key, crc_extra=crc_extra, clock=clock)
        self._metric = refused_metric
        self.downlink_frames = 0
        self.downlink_dropped = 0
        self.uplink_frames = 0
        self.uplink_dropped = 0
        self.answers = 0
        self.refused: Counter[str] = Counter()
        self._log_limit = RateLimit(interval_s=10.0)

    # -- downlink ---------------------------------------------------------------------------

    def forward(self, frame: bytes) -> None:
        """Copy one accepted frame from the airframe to the endpoint (never raises)."""
        if self._signer is not None:
            if frame[:1] != bytes([_STX_V2]):
                self.downlink_dropped += 1  # MAVLink 1 cannot be signed
                return
            try:
                frame = self._signer.sign(frame)
            except FrameError:
                self.downlink_dropped += 1
                return
        if self.link.send_nowait(frame):
            self.downlink_frames += 1

    # -- uplink -----------------------------------------------------------------------------

    def _from_gcs(self, _label: str, peer: object, data: bytes) -> None:
        if self._send is None or not isinstance(peer, tuple):
            return
        try:
            if (
                peer not in self.link.peers
                and self._send.statistics().current_buffer_used >= _STRANGER_QUEUE
            ):
                raise anyio.WouldBlock
            self._send.send_nowait((peer, data))
        except (anyio.WouldBlock, anyio.BrokenResourceError, anyio.ClosedResourceError):
            self.uplink_dropped += 1
            if self._log_limit.allow("full"):
                log.warning(
                    "passthrough_uplink_dropped",
                    airframe=self.airframe,
                    reason="uplink queue full",
                    dropped_total=self.uplink_dropped,
                )

    async def run(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Bind the endpoint and relay ground-station traffic until cancelled."""
        send, receive = anyio.create_memory_object_stream[tuple[Peer, bytes]](_UPLINK_QUEUE)
        self._send = send
        if self.uplink == "open":
            log.warning(
                "passthrough_uplink_open",
                airframe=self.airframe,
                uri=str(self.config.uri),
                note="any local process may send to this airframe (within the command policy)",
            )
        async with send, receive, anyio.create_task_group() as tg:
            await tg.start(self.link.run)
            task_status.started()
            async for peer, data in receive:
                try:
                    await self.receive(peer, data)
                except Exception as exc:  # no datagram may end the daemon (logged below)
                    self._refuse(peer, Refusal("internal_error", type(exc).__name__))
                    # Its own key: the refusal above already took the "internal_error" one.
                    if self._log_limit.allow("internal_error_traceback"):
                        log.exception("passthrough_internal_error", airframe=self.airframe)

    async def receive(self, peer: Peer, data: bytes) -> None:
        """Handle one datagram from a ground station at ``peer`` (``run`` does, for each)."""
        if len(data) > MAX_DATAGRAM_BYTES:
            self._refuse(peer, Refusal("oversize", f"{len(data)} bytes in one datagram"))
            return
        parser = self._parser
        before = (parser.bad, parser.unknown, parser.truncated)
        try:
            messages = parser.feed(data, whole=True)
        except FrameError as exc:
            self._refuse(peer, Refusal("malformed", str(exc)))
            return
        for reason, was, now in zip(
            ("malformed", "unknown_msgid", "truncated"),
            before,
            (parser.bad, parser.unknown, parser.truncated),
            strict=True,
        ):
            if now > was:
                self._refuse(peer, Refusal(reason, "not a whole MAVLink 2 frame with a good CRC"))
        for msg in messages:
            await self._frame(peer, msg)

    async def _frame(self, peer: Peer, msg: Any) -> None:
        raw = bytes(msg.get_msgbuf())
        if raw[0] != _STX_V2:
            self._refuse(peer, Refusal("mavlink1", "MAVLink 1 frame: set the ground station to 2"))
            return
        if self._verifier is not None:
            try:
                self._verifier.verify(raw)
            except FrameError as exc:
                hint = (
                    "; a ground station signs with the passthrough's key_file (docs/security.md)"
                    if exc.reason == "auth"
                    else ""
                )
                self._refuse(peer, Refusal(f"signature_{exc.reason}", f"{exc}{hint}"))
                return
        if msg.get_srcSystem() == self.sysid:
            # The airframe's own frames, signed with the station's key on their way out,
            # would verify if a squatter on the station's port sent them back.
            self._refuse(
                peer,
                Refusal("airframe_source", f"a ground station cannot be system {self.sysid}"),
                msg,
            )
            return
        self.link.learn_peer(peer)
        refusal = check(
            msg, sysid=self.sysid, uplink=self.uplink, param_set_allow=self.config.param_set_allow
        )
        if refusal is not None:
            self._refuse(peer, refusal, msg)
            await self._answer(peer, msg)
            return
        await self._relay(peer, self._reserialise(msg))

    def _reserialise(self, msg: Any) -> bytes:
        """A new MAVLink 2 frame from the message's parsed fields (unsigned, CRC recomputed)."""
        return self._pack(msg, msg.get_srcSystem(), msg.get_srcComponent(), msg.get_seq())

    def _pack(self, msg: Any, sysid: int, compid: int, seq: int = 0) -> bytes:
        """``msg`` as a MAVLink 2 frame from ``sysid``/``compid``."""
        packer = self._packer
        packer.srcSystem, packer.srcComponent, packer.seq = sysid, compid, seq
        return bytes(msg.pack(packer))

    async def _relay(self, peer: Peer, frame: bytes) -> bool:
        try:
            await self._send_to_airframe(self.airframe, frame)
        except GatewayError as exc:
            self.uplink_dropped += 1
            if self._log_limit.allow("link"):
                log.warning(
                    "passthrough_uplink_failed",
                    airframe=self.airframe,
                    sender=_sender(peer),
                    error=str(exc),
                    dropped_total=self.uplink_dropped,
                )
            return False
        self.uplink_frames += 1
        return True

    async def _answer(self, peer: Peer, msg: Any) -> None:
        """Answer a refused command or mission item so the ground station stops waiting."""
        msgid = msg.get_msgId()
        src, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        compid = getattr(msg, "target_component", 0) or _AUTOPILOT_COMPID
        packer = self._packer
        if msgid in COMMAND_MSGS:
            answer = packer.command_ack_encode(
                msg.command, dialect.MAV_RESULT_DENIED, 0, 0, src, src_comp
            )
        elif msgid in MISSION_ITEM_MSGS:
            mission_type = int(getattr(msg, "mission_type", 0))
            answer = packer.mission_ack_encode(
                src, src_comp, dialect.MAV_MISSION_DENIED, mission_type
            )
            if self.uplink != "none":
                # The airframe is waiting for this item: cancel the upload on the
                # station's behalf rather than leave it to time out.
                cancel = packer.mission_ack_encode(
                    self.sysid, compid, dialect.MAV_MISSION_OPERATION_CANCELLED, mission_type
                )
                await self._relay(peer, self._pack(cancel, src, src_comp))
        else:
            return
        frame = self._pack(answer, self.sysid, compid)
        if self._signer is not None:
            frame = self._signer.sign(frame)
        try:
            await self.link.send_to(peer, frame)
        except GatewayError:
            return  # the endpoint is closing: nobody to answer
        self.answers += 1

    def _refuse(self, peer: Peer, refusal: Refusal, msg: Any = None) -> None:
        self.refused[refusal.reason] += 1
        if self._metric is not None:
            self._metric.labels(self.airframe, refusal.reason).inc()
        if self._log_limit.allow(refusal.reason):
            log.warning(
                "passthrough_uplink_refused",
                airframe=self.airframe,
                uplink=self.uplink,
                sender=_sender(peer),
                reason=refusal.reason,
                detail=refusal.detail,
                message=None if msg is None else msg.get_type(),
                refused_total=self.refused[refusal.reason],
            )

    def status(self) -> dict[str, object]:
        """Counters for /status."""
        return {
            "airframe": self.airframe,
            "uri": str(self.link.endpoint),
            "uplink": self.uplink,
            "ground_stations": [_sender(peer) for peer in self.link.peers],
            "downlink_frames": self.downlink_frames,
            "downlink_dropped": self.downlink_dropped,
            "uplink_frames": self.uplink_frames,
            "uplink_dropped": self.uplink_dropped,
            "uplink_refused": sum(self.refused.values()),
            "refused": dict(sorted(self.refused.items())),
            "answers": self.answers,
        }


def _sender(peer: Peer) -> str:
    return f"{peer[0]}:{peer[1]}"
