"""The KLV sink: STANAG 4609 motion-imagery metadata (MISB ST 0601) for video clients.

Each ``VideoFrameMetadata`` becomes one ST 0601 UAS Datalink Local Set packet
(``sinks.klv``). Where it goes, any or all of:

- ``udp``: each packet as one datagram (unicast, or a multicast group with ``ttl`` and
  ``interface``), what KLV-aware viewers and georegistration tools listen for;
- ``mpegts``: a transport stream with the packets as an asynchronous KLV data stream (ST
  1402), sent over UDP in datagrams of seven 188-byte packets. With ``video`` set, ffmpeg
  (a subprocess run for the sink's lifetime) reads the airframe's video from that URL and
  writes video and KLV together to the ``mpegts`` destination; the video is copied, never
  re-encoded. Give each airframe its own KLV sink then, with a route naming that airframe.

The sink keeps no delivery state: metadata is latest-wins, and a failure raises
``TransientSinkError`` naming the sink; an ffmpeg that exits is reported by the sink's
lifetime, so the runner reopens the sink (and ffmpeg) with backoff.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence

import anyio
import anyio.abc
import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, model_validator

from gateway.c2.sink import SinkConfig
from gateway.errors import TransientSinkError
from gateway.events import Event, EventKind, VideoFrameMetadata
from gateway.transports.udp import DatagramSender
from sinks.klv.mpegts import TS_PACKET_BYTES, KlvTsMuxer, pts_90khz
from sinks.klv.uas import frame_packet
from sinks.klv.video import VideoMuxer, ffmpeg_command

__all__ = ["KlvMpegTs", "KlvSink", "KlvSinkConfig", "KlvUdp"]

log = structlog.get_logger(__name__)

_FROZEN = ConfigDict(frozen=True, extra="forbid")
_TS_PER_DATAGRAM = 7  # 1316 bytes: the usual MPEG-TS over UDP payload


class KlvUdp(BaseModel):
    """A UDP destination: a host or multicast group and port."""

    model_config = _FROZEN

    host: str = Field(min_length=1, description="Address, name or multicast group.")
    port: int = Field(ge=1, le=65535, description="UDP port.")
    ttl: int = Field(default=1, ge=0, le=255, description="Multicast TTL.")
    interface: str | None = Field(default=None, description="Multicast interface (address/name).")


class KlvMpegTs(KlvUdp):
    """MPEG-TS out over UDP, alone (KLV only) or beside the airframe's video through ffmpeg."""

    video: str | None = Field(
        default=None,
        description="The airframe's video (an ffmpeg input URL or file): muxed with the KLV.",
    )
    video_realtime: bool = Field(
        default=False, description="Read the video at its own rate (for a file, not a live feed)."
    )
    ffmpeg: str = Field(default="ffmpeg", description="The ffmpeg executable.")

    @model_validator(mode="after")
    def _ffmpeg_found(self, info: ValidationInfo) -> KlvMpegTs:
        # On the node only (run, check-config): not with ``check-config --no-environment``.
        on_node = isinstance(info.context, dict) and info.context.get("environment")
        if on_node and self.video is not None and shutil.which(self.ffmpeg) is None:
            raise ValueError(f"video needs ffmpeg, and {self.ffmpeg!r} is not on the PATH")
        return self


class KlvSinkConfig(SinkConfig):
    """Options of the KLV sink (``sinks[].options``)."""

    udp: KlvUdp | None = Field(default=None, description="ST 0601 packets, one per datagram.")
    mpegts: KlvMpegTs | None = Field(default=None, description="MPEG-TS with a KLV stream.")
    mission_id: str | None = Field(default=None, max_length=127, description="ST 0601 tag 3.")
    platform_designation: str = Field(
        default="Fischer 26E", min_length=1, max_length=127, description="ST 0601 tag 10."
    )

    @model_validator(mode="after")
    def _somewhere(self) -> KlvSinkConfig:
        if self.udp is None and self.mpegts is None:
            raise ValueError("give udp, mpegts or both")
        return self


class KlvSink:
    """Sends ``VideoFrameMetadata`` as ST 0601 KLV over UDP and in MPEG-TS."""

    config_model = KlvSinkConfig

    def __init__(self, name: str, config: KlvSinkConfig) -> None:
        self.name = name
        self.config = config
        self.log = log.bind(sink=name)
        self._udp = None if config.udp is None else _sender(config.udp)
        ts = config.mpegts
        self._ts_udp = None if ts is None or ts.video is not None else _sender(ts)
        self._video: VideoMuxer | None = None
        self._muxer = KlvTsMuxer()
        self._pending_ts = bytearray()

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Video frame metadata only."""
        return frozenset({EventKind.VIDEO_FRAME_METADATA})

    async def open(self) -> None:
        """Open the sockets and start ffmpeg when there is a video; ``TransientSinkError``."""
        self._muxer = KlvTsMuxer()  # a new stream: PAT and PMT first
        self._pending_ts.clear()
        try:
            for sender in (self._udp, self._ts_udp):
                if sender is not None:
                    await sender.open()
        except OSError as exc:
            raise self._error("open", exc) from exc
        ts = self.config.mpegts
        if ts is not None and ts.video is not None:
            command = ffmpeg_command(ts.ffmpeg, ts.video, _udp_url(ts), realtime=ts.video_realtime)
            self._video = VideoMuxer(command, self.name)
            await self._video.start()
            self.log.info("klv_video_muxer_started", video=ts.video)

    async def run(self, *, task_status: anyio.abc.TaskStatus[None]) -> None:
        """While ffmpeg runs, read its errors; raise when it exits (the runner reopens)."""
        task_status.started()
        if self._video is not None:
            await self._video.wait()
        else:
            await anyio.sleep_forever()

    async def send(self, batch: Sequence[Event]) -> None:
        """Encode and send every frame's metadata; ``TransientSinkError`` if refused."""
        for event in batch:
            if not isinstance(event, VideoFrameMetadata):
                continue
            packet = frame_packet(
                event,
                mission_id=self.config.mission_id,
                platform_designation=self.config.platform_designation,
            )
            try:
                if self._udp is not None:
                    await self._udp.send(packet)
                if self.config.mpegts is not None:
                    await self._send_ts(self._muxer.mux(packet, pts_90khz(event.time)))
            except OSError as exc:
                raise self._error("send", exc) from exc

    async def _send_ts(self, data: bytes) -> None:
        if self._video is not None:
            await self._video.write(data)
            return
        if self._ts_udp is None:
            return
        # Whole datagrams of seven TS packets, as receivers expect; the rest waits.
        self._pending_ts += data
        size = TS_PACKET_BYTES * _TS_PER_DATAGRAM
        while len(self._pending_ts) >= size:
            await self._ts_udp.send(bytes(self._pending_ts[:size]))
            del self._pending_ts[:size]

    async def aclose(self) -> None:
        """Flush the last TS datagram, stop ffmpeg, close the sockets; safe when not open."""
        video, self._video = self._video, None
        if video is not None:
            await video.aclose()
        if self._ts_udp is not None and self._pending_ts:
            try:
                with anyio.move_on_after(1.0):
                    await self._ts_udp.send(bytes(self._pending_ts))
            except OSError as exc:
                self.log.warning("klv_ts_flush_failed", reason=exc.strerror or str(exc))
            self._pending_ts.clear()
        for sender in (self._udp, self._ts_udp):
            if sender is not None:
                await sender.aclose()

    def _error(self, action: str, exc: OSError) -> TransientSinkError:
        return TransientSinkError(
            f"sink {self.name}: cannot {action}: {exc.strerror or exc}", sink=self.name
        )


def _sender(destination: KlvUdp) -> DatagramSender:
    return DatagramSender(
        destination.host, destination.port, ttl=destination.ttl, interface=destination.interface
    )


def _udp_url(destination: KlvMpegTs) -> str:
    query = f"?pkt_size={TS_PACKET_BYTES * _TS_PER_DATAGRAM}&ttl={destination.ttl}"
    host = f"[{destination.host}]" if ":" in destination.host else destination.host
    return f"udp://{host}:{destination.port}{query}"
