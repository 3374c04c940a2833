"""The JSONL archive sink: one event per line, rotated by size and age, pruned by count.

Lines end with ``\n`` only; read them with ``split("\n")``, not ``str.splitlines()``,
which also splits on the Unicode separators JSON leaves unescaped. A rotated file is named
after the time it was started.
"""

from __future__ import annotations

import errno
import os
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path

import anyio
import structlog
from pydantic import Field

from gateway.errors import TransientSinkError
from gateway.events import Event, EventKind
from gateway.sink import SinkConfig

__all__ = ["JsonlSink", "JsonlSinkConfig"]

log = structlog.get_logger(__name__)


class JsonlSinkConfig(SinkConfig):
    """Options of the JSONL archive."""

    path: Path
    max_bytes: int = Field(default=100 * 1024 * 1024, ge=1024)
    max_age_s: float = Field(default=86_400.0, gt=0)
    keep: int = Field(default=30, ge=0, description="Rotated files kept; older are deleted.")
    fsync: bool = Field(default=False, description="fsync after every batch (slower, safer).")
    kinds: frozenset[EventKind] = frozenset(EventKind)


class JsonlSink:
    """Appends events to ``path``; blocking file work runs in a worker thread per batch."""

    config_model = JsonlSinkConfig

    def __init__(
        self, name: str, config: JsonlSinkConfig, *, clock: Callable[[], float] = time.time
    ) -> None:
        self.name = name
        self.config = config
        self._clock = clock
        self._path = config.path
        self._file: int | None = None
        self._size = 0
        self._opened_at = 0.0

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Every kind unless the config narrows it."""
        return self.config.kinds

    def _error(self, action: str, exc: OSError) -> TransientSinkError:
        full = " (disk full)" if exc.errno == errno.ENOSPC else ""
        return TransientSinkError(
            f"sink {self.name}: cannot {action} {self._path}: {exc.strerror}{full}", sink=self.name
        )

    def _open_file(self) -> None:
        self._path = self.config.path.resolve()
        self._path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self._path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o640)
        size = os.fstat(fd).st_size
        if size:
            # A crash mid-line leaves a partial last line: end it so the next one parses.
            with self._path.open("rb") as handle:
                handle.seek(size - 1)
                if handle.read(1) != b"\n":
                    size += os.write(fd, b"\n")
        self._file, self._size, self._opened_at = fd, size, self._clock()

    async def open(self) -> None:
        """Open (or create) the archive file for appending."""
        try:
            await anyio.to_thread.run_sync(self._open_file)
        except OSError as exc:
            raise self._error("open", exc) from exc

    def _rotated_name(self) -> Path:
        stamp = datetime.fromtimestamp(self._opened_at, tz=UTC).strftime("%Y%m%dT%H%M%SZ")
        stem = self._path.stem
        candidate = self._path.with_name(f"{stem}-{stamp}{self._path.suffix}")
        counter = 1
        while candidate.exists():
            candidate = self._path.with_name(f"{stem}-{stamp}-{counter}{self._path.suffix}")
            counter += 1
        return candidate

    def _rotate(self) -> None:
        assert self._file is not None  # noqa: S101 - only called while open
        os.close(self._file)
        self._file = None
        os.rename(self._path, self._rotated_name())
        rotated = sorted(
            self._path.parent.glob(f"{self._path.stem}-*{self._path.suffix}"),
            key=lambda p: p.stat().st_mtime,
        )
        for old in rotated[: max(0, len(rotated) - self.config.keep)]:
            old.unlink(missing_ok=True)
        log.info("archive_rotated", sink=self.name, kept=min(len(rotated), self.config.keep))
        self._open_file()

    def _write(self, data: bytes) -> None:
        if self._file is None:
            self._open_file()
        if self._size and (
            self._size + len(data) > self.config.max_bytes
            or self._clock() - self._opened_at >= self.config.max_age_s
        ):
            self._rotate()
        assert self._file is not None  # noqa: S101 - opened above
        view = memoryview(data)
        while view:
            written = os.write(self._file, view)
            view = view[written:]
        self._size += len(data)
        if self.config.fsync:
            os.fsync(self._file)

    async def send(self, batch: Sequence[Event]) -> None:
        """Append the batch, one JSON line per event, in one write."""
        data = b"".join(event.model_dump_json().encode() + b"\n" for event in batch)
        try:
            await anyio.to_thread.run_sync(self._write, data)
        except OSError as exc:
            raise self._error("write", exc) from exc

    async def aclose(self) -> None:
        """Close the file."""
        if self._file is not None:
            fd, self._file = self._file, None
            await anyio.to_thread.run_sync(os.close, fd)
