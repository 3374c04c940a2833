"""The ffmpeg subprocess that puts our KLV stream beside an airframe's video (STANAG 4609).

ffmpeg reads the video from ``input`` (a URL or file it understands) and our KLV-only
transport stream from its stdin, and writes one MPEG-TS with both, the video copied
untouched and the KLV as an asynchronous KLV data stream, to ``output``. Nothing of the
video is decoded or re-encoded. ffmpeg's stderr is read (so it never blocks on a full pipe)
and its last lines are kept for the error when it exits.
"""

from __future__ import annotations

import contextlib
import subprocess
from collections import deque

import anyio
import anyio.abc
import structlog

from gateway.errors import TransientSinkError

__all__ = ["VideoMuxer", "ffmpeg_command"]

log = structlog.get_logger(__name__)

_STDERR_LINES = 20


def ffmpeg_command(
    ffmpeg: str, video_input: str, output: str, *, realtime: bool = False
) -> list[str]:
    """The ffmpeg command line: video from ``video_input``, KLV from stdin, to ``output``."""
    video = ["-re"] if realtime else []
    return [
        ffmpeg, "-hide_banner", "-nostdin", "-loglevel", "error",
        *video, "-i", video_input,
        # Our stream announces its KLV stream in the first PMT: nothing to probe for.
        "-probesize", "2048", "-analyzeduration", "0", "-f", "mpegts", "-i", "pipe:0",
        "-map", "0:v:0", "-map", "1:d:0", "-c", "copy",
        "-flush_packets", "1", "-muxdelay", "0", "-f", "mpegts", output,
    ]  # fmt: skip


class VideoMuxer:
    """One ffmpeg process for one sink: ``start``, ``write`` TS bytes, ``wait``, ``aclose``."""

    def __init__(self, command: list[str], sink: str) -> None:
        self.command = command
        self.sink = sink
        self._process: anyio.abc.Process | None = None
        self.stderr: deque[str] = deque(maxlen=_STDERR_LINES)

    @property
    def is_running(self) -> bool:
        """True while ffmpeg runs."""
        return self._process is not None and self._process.returncode is None

    async def start(self) -> None:
        """Start ffmpeg; ``TransientSinkError`` if it cannot be started."""
        try:
            self._process = await anyio.open_process(
                self.command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL
            )
        except OSError as exc:
            raise TransientSinkError(
                f"sink {self.sink}: cannot start {self.command[0]}: {exc.strerror or exc}",
                sink=self.sink,
            ) from exc

    async def write(self, data: bytes) -> None:
        """Give ffmpeg transport stream bytes; ``TransientSinkError`` once it has gone."""
        process = self._process
        if process is None or process.stdin is None or process.returncode is not None:
            raise self._gone()
        try:
            await process.stdin.send(data)
        except (anyio.BrokenResourceError, anyio.ClosedResourceError, OSError) as exc:
            raise self._gone() from exc

    async def wait(self) -> None:
        """Read ffmpeg's stderr until it exits, then raise ``TransientSinkError`` saying why."""
        process = self._process
        if process is None:
            raise self._gone()
        if process.stderr is not None:
            buffer = b""
            with contextlib.suppress(anyio.EndOfStream, anyio.BrokenResourceError):
                async for chunk in process.stderr:
                    buffer = (buffer + chunk)[-4096:]
                    *lines, buffer = buffer.split(b"\n")
                    self.stderr.extend(line.decode(errors="replace") for line in lines if line)
        await process.wait()
        raise self._gone()

    def _gone(self) -> TransientSinkError:
        process = self._process
        code = None if process is None else process.returncode
        tail = self.stderr[-1] if self.stderr else "no output"
        return TransientSinkError(
            f"sink {self.sink}: ffmpeg is not running (exit {code}): {tail}", sink=self.sink
        )

    async def aclose(self) -> None:
        """End ffmpeg's input, give it a moment to finish the file, then stop it."""
        process, self._process = self._process, None
        if process is None:
            return
        with anyio.CancelScope(shield=True):
            if process.stdin is not None:
                with contextlib.suppress(OSError, anyio.BrokenResourceError):
                    await process.stdin.aclose()
            with anyio.move_on_after(2.0):
                await process.wait()
            if process.returncode is None:
                process.terminate()
                with anyio.move_on_after(2.0):
                    await process.wait()
            if process.returncode is None:
                process.kill()
                await process.wait()
            await process.aclose()
