"""The ffmpeg subprocess that puts our KLV stream beside an airframe's video (STANAG 4609).

ffmpeg reads the video from ``input`` (a URL or file it understands) and our KLV-only
transport stream from its stdin, and writes one MPEG-TS with both, the video copied
untouched and the KLV as an asynchronous KLV data stream, to ``output``. Nothing of the
video is decoded or re-encoded. ffmpeg's stderr is read (so it never blocks on a full pipe)
and its last lines are kept for the error when it exits.

Writes never wait for ffmpeg: KLV it cannot take now is dropped, so the sink's other
destinations (UDP) never slow down with it. An ffmpeg that takes nothing from its stdin for
``STALL_S`` (stopped, or hung) is killed: the sink's lifetime then ends and the runner
starts a new one, instead of a process that will never read again holding the sink. A UDP
video input is given ffmpeg's own read ``timeout`` (``INPUT_TIMEOUT_S``) and ``-shortest``
ends ffmpeg with its video, so a camera that goes silent ends ffmpeg with a reason rather
than leaving it waiting forever or carrying on with KLV alone.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import select
import subprocess
import time
from collections import deque

import anyio
import anyio.abc
import anyio.lowlevel
import structlog

from gateway.errors import TransientSinkError

__all__ = ["VideoMuxer", "ffmpeg_command"]

log = structlog.get_logger(__name__)

_STDERR_LINES = 20
#: A pipe ffmpeg has taken nothing from for this long means it is stuck: it is killed. Longer
#: than ffmpeg's probing of the video at its start, when it reads nothing from us.
STALL_S = 10.0
#: A UDP video input silent for this long ends ffmpeg (its ``timeout`` option).
INPUT_TIMEOUT_S = 5.0
#: ffmpeg's stdin pipe: about a second of KLV at 30 packets a second.
PIPE_BYTES = 16_384
#: Whole TS packets in one write no longer than PIPE_BUF: the pipe takes all of it or none.
_ATOMIC_WRITE = 188 * (select.PIPE_BUF // 188)


def ffmpeg_command(
    ffmpeg: str, video_input: str, output: str, *, realtime: bool = False
) -> list[str]:
    """The ffmpeg command line: video from ``video_input``, KLV from stdin, to ``output``."""
    video = ["-re"] if realtime else []
    if video_input.startswith("udp://"):
        # ffmpeg's udp protocol waits for ever by default; its ``timeout`` is in microseconds.
        video += ["-timeout", str(round(INPUT_TIMEOUT_S * 1e6))]
    return [
        ffmpeg, "-hide_banner", "-nostdin", "-loglevel", "error",
        *video, "-i", video_input,
        # Our stream announces its KLV stream in the first PMT: nothing to probe for.
        "-probesize", "2048", "-analyzeduration", "0", "-f", "mpegts", "-i", "pipe:0",
        # -shortest: the video ending (a silent camera's timeout) ends ffmpeg, not the video.
        "-map", "0:v:0", "-map", "1:d:0", "-c", "copy", "-shortest",
        "-flush_packets", "1", "-muxdelay", "0", "-f", "mpegts", output,
    ]  # fmt: skip


class VideoMuxer:
    """One ffmpeg process for one sink: ``start``, ``write`` TS bytes, ``wait``, ``aclose``.

    ffmpeg's stdin is a non-blocking pipe of our own with no buffer of ours in front of it,
    shrunk to ``PIPE_BYTES`` where Linux allows: what ffmpeg has not read yet is bounded, and
    a stall shows within seconds even at a few packets a second.
    """

    def __init__(self, command: list[str], sink: str, *, stall_s: float = STALL_S) -> None:
        self.command = command
        self.sink = sink
        self.stall_s = stall_s
        self._stalled = False
        self._last_taken = time.monotonic()
        #: Writes cut short because ffmpeg's pipe was full.
        self.dropped = 0
        self._process: anyio.abc.Process | None = None
        self._stdin: int | None = None
        self.stderr: deque[str] = deque(maxlen=_STDERR_LINES)

    @property
    def is_running(self) -> bool:
        """True while ffmpeg runs."""
        return self._process is not None and self._process.returncode is None

    async def start(self) -> None:
        """Start ffmpeg; ``TransientSinkError`` if it cannot be started."""
        read_end, write_end = os.pipe()
        try:
            with contextlib.suppress(OSError, AttributeError):  # Linux only; else 64 KiB
                fcntl.fcntl(write_end, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
            os.set_blocking(write_end, False)
            self._process = await anyio.open_process(
                self.command, stdin=read_end, stdout=subprocess.DEVNULL
            )
        except OSError as exc:
            os.close(write_end)
            raise TransientSinkError(
                f"sink {self.sink}: cannot start {self.command[0]}: {exc.strerror or exc}",
                sink=self.sink,
            ) from exc
        finally:
            os.close(read_end)
        self._stdin = write_end
        self._last_taken = time.monotonic()

    async def write(self, data: bytes) -> None:
        """Give ffmpeg transport stream bytes; ``TransientSinkError`` once it has gone.

        Never waits for ffmpeg: what its full pipe cannot take now is dropped (metadata is
        latest-wins, and ffmpeg reads nothing while it probes the video), in whole TS
        packets. A pipe that has taken nothing for ``stall_s`` kills ffmpeg (see the module
        docstring).
        """
        process, fd = self._process, self._stdin
        if process is None or fd is None or process.returncode is not None:
            raise self._gone()
        now = time.monotonic()
        for start in range(0, len(data), _ATOMIC_WRITE):
            try:
                os.write(fd, data[start : start + _ATOMIC_WRITE])  # all or nothing
            except BlockingIOError:
                self.dropped += 1
                if now - self._last_taken > self.stall_s:
                    self._stalled = True
                    self._kill(process)
                    raise self._gone() from None
                return
            except OSError as exc:  # EPIPE: ffmpeg has gone
                raise self._gone() from exc
            self._last_taken = now
        await anyio.lowlevel.checkpoint()

    @staticmethod
    def _kill(process: anyio.abc.Process) -> None:
        # SIGKILL ends a stopped process too; ``wait`` (the sink's lifetime) reaps it.
        with contextlib.suppress(ProcessLookupError):
            process.kill()

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
        if self._stalled:
            tail = f"it took no input for {self.stall_s} s and was stopped"
        return TransientSinkError(
            f"sink {self.sink}: ffmpeg is not running (exit {code}): {tail}", sink=self.sink
        )

    async def aclose(self) -> None:
        """End ffmpeg's input, give it a moment to finish the file, then stop it."""
        process, self._process = self._process, None
        fd, self._stdin = self._stdin, None
        if fd is not None:
            os.close(fd)  # the end of ffmpeg's input: it finishes the stream and exits
        if process is None:
            return
        with anyio.CancelScope(shield=True):
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
