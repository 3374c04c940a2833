"""A serial port written through the event loop, without a thread: raw 8N1 at a given baud.

``SerialWriter`` opens the device non-blocking (``O_NOCTTY``), sets it raw so no line
discipline touches the bytes, and writes each frame whole, waiting while the driver's buffer
is full. Any failure is an ``OSError`` naming the device: the caller decides to retry (a USB
radio data terminal unplugged and plugged back is reopened by the next ``open``). It uses
``os`` and ``termios`` directly rather than pyserial: one non-blocking descriptor the event
loop can wait on, and no dependency. ``open_raw`` is also how the airframes' serial links
(``gateway.fleet.links``) open their devices.
"""

from __future__ import annotations

import os
import termios

import anyio

__all__ = ["SerialWriter", "is_supported_baud"]


def is_supported_baud(baud: int) -> bool:
    """True if this platform's termios has a speed constant for ``baud``."""
    return isinstance(getattr(termios, f"B{baud}", None), int)


def open_raw(device: str, baud: int) -> int:
    """The descriptor of ``device`` opened non-blocking and set to raw 8N1 at ``baud``.

    Raises ``OSError`` naming the device (missing, not a terminal, no such speed).
    """
    speed = getattr(termios, f"B{baud}", None)
    if not isinstance(speed, int):
        raise OSError(f"{device}: unsupported baud rate {baud}")
    fd = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        attrs = termios.tcgetattr(fd)
        attrs[0] = 0  # iflag: no input processing
        attrs[1] = 0  # oflag: no output processing (CR LF are sent as given)
        attrs[2] = termios.CS8 | termios.CREAD | termios.CLOCAL
        attrs[3] = 0  # lflag: no echo, not canonical
        attrs[4] = attrs[5] = speed
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except termios.error as exc:
        os.close(fd)
        raise OSError(f"{device} is not a terminal device: {exc}") from exc
    except OSError:
        os.close(fd)
        raise
    return fd


class SerialWriter:
    """One serial device to write frames to; ``OSError`` from ``open``/``write`` on failure."""

    def __init__(self, device: str, baud: int, *, write_timeout_s: float = 10.0) -> None:
        self.device = device
        self.baud = baud
        self.write_timeout_s = write_timeout_s
        self._fd: int | None = None

    @property
    def is_open(self) -> bool:
        """True while the device is open."""
        return self._fd is not None

    def open(self) -> None:
        """Open the device if it is not open; ``OSError`` naming it if that fails."""
        if self._fd is None:
            self._fd = open_raw(self.device, self.baud)

    async def write(self, data: bytes) -> None:
        """Write ``data`` whole, opening the device first if needed.

        ``OSError`` if the device fails or takes longer than ``write_timeout_s`` (a terminal
        holding flow control forever); the device is closed then, and opened again next time.
        """
        self.open()
        fd = self._fd
        assert fd is not None  # noqa: S101 - open() set it or raised
        view = memoryview(data)
        try:
            with anyio.fail_after(self.write_timeout_s):
                while view:
                    await anyio.wait_writable(fd)
                    try:
                        written = os.write(fd, view)
                    except BlockingIOError:
                        continue
                    view = view[written:]
        except TimeoutError as exc:
            self.close()
            raise OSError(f"{self.device}: write timed out after {self.write_timeout_s} s") from exc
        except OSError as exc:
            self.close()
            raise OSError(f"{self.device}: write failed: {exc.strerror or exc}") from exc

    def close(self) -> None:
        """Close the device; safe when it is not open."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)
