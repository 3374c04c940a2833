"""Key material from files and systemd credentials, and day-key files for airframes.

Keys are read from files that must not be readable by group or others (``chmod 600``), or
from a systemd credential (``LoadCredential=``, read from ``$CREDENTIALS_DIRECTORY``). A key
file holds raw bytes or hex text. Nothing here ever logs key bytes.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Mapping
from datetime import date, timedelta
from pathlib import Path

from gateway.errors import ConfigError, ConfigIssue
from gateway.fleet.security.tunnel import derive_day_key

__all__ = ["load_day_keys", "read_credential", "read_key_file", "write_day_keys"]


def _problem(path: Path, message: str) -> ConfigError:
    return ConfigError([ConfigIssue(str(path), None, "(key file)", message)])


#: Largest key file read: a key is 32 bytes, or 64 hex digits and a newline.
MAX_KEY_FILE_BYTES = 4096


def _read_small_file(path: Path, what: str, *, check_mode: bool) -> bytes:
    """Read a regular file of at most ``MAX_KEY_FILE_BYTES``, checked *before* reading."""
    try:
        # O_NONBLOCK: opening a FIFO someone put in the key's place must not hang start-up.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise _problem(path, f"cannot read {what}: {exc.strerror}") from exc
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            kind = "a directory" if stat.S_ISDIR(info.st_mode) else "not a regular file"
            raise _problem(path, f"{what} is {kind}")
        if check_mode and info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            mode = stat.S_IMODE(info.st_mode)
            raise _problem(path, f"{what} mode is {mode:o}; expected 600 or stricter")
        if info.st_size > MAX_KEY_FILE_BYTES:
            raise _problem(
                path, f"{what} is {info.st_size} bytes; a key file is at most {MAX_KEY_FILE_BYTES}"
            )
        try:
            data = os.read(fd, MAX_KEY_FILE_BYTES + 1)
        except OSError as exc:
            raise _problem(path, f"cannot read {what}: {exc.strerror}") from exc
        if len(data) != info.st_size:
            # /proc and /sys files say "regular, 0 bytes" and then produce text.
            raise _problem(path, f"{what} is not a regular file (its size changes as it is read)")
        return data
    finally:
        os.close(fd)


def read_key_file(path: Path, *, min_bytes: int = 32, exact: bool = False) -> bytes:
    """Read a key from ``path``: raw bytes or hex text.

    Refuses, before reading a byte, anything but a regular file, a file group or others may
    access, and a file over ``MAX_KEY_FILE_BYTES``.
    """
    data = _read_small_file(path, "key file", check_mode=True)
    text = data.strip()
    try:
        key = bytes.fromhex(text.decode("ascii")) if text else b""
    except (UnicodeDecodeError, ValueError):
        key = data
    if len(key) < min_bytes or (exact and len(key) != min_bytes):
        wanted = f"exactly {min_bytes}" if exact else f"at least {min_bytes}"
        raise _problem(
            path,
            f"expected {wanted} key bytes (raw, or written as {2 * min_bytes} hex digits), "
            f"found {len(key)}",
        )
    return key


def read_credential(name: str, env: Mapping[str, str] | None = None) -> bytes:
    """Read systemd credential ``name`` (a master key) from ``$CREDENTIALS_DIRECTORY``."""
    env = os.environ if env is None else env
    directory = env.get("CREDENTIALS_DIRECTORY")
    if not directory:
        raise ConfigError(
            [
                ConfigIssue(
                    "(environment)",
                    None,
                    "tunnel.master_key_credential",
                    f"credential {name!r} configured but CREDENTIALS_DIRECTORY is not set "
                    "(run under systemd with LoadCredential=)",
                )
            ]
        )
    # systemd makes credential files readable by the service only; no mode check needed.
    path = Path(directory) / name
    data = _read_small_file(path, "credential", check_mode=False)
    text = data.strip()
    try:
        return bytes.fromhex(text.decode("ascii"))
    except (UnicodeDecodeError, ValueError):
        return data


def _day_key_path(directory: Path, airframe: str, day: date) -> Path:
    return directory / f"{airframe}-{day.isoformat()}.key"


def write_day_keys(
    master: bytes, airframe: str, first: date, days: int, directory: Path
) -> list[Path]:
    """Write ``days`` day keys of ``airframe`` from ``first`` as hex files, mode 0600."""
    directory.mkdir(parents=True, exist_ok=True, mode=0o700)
    written = []
    for offset in range(days):
        day = first + timedelta(days=offset)
        path = _day_key_path(directory, airframe, day)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as handle:
            handle.write(derive_day_key(master, airframe, day).hex() + "\n")
        written.append(path)
    return written


def load_day_keys(directory: Path, airframe: str) -> dict[tuple[str, date], bytes]:
    """Every day key of ``airframe`` in ``directory`` (as written by ``write_day_keys``)."""
    keys: dict[tuple[str, date], bytes] = {}
    for path in sorted(directory.glob(f"{airframe}-????-??-??.key")):
        day = date.fromisoformat(path.stem[len(airframe) + 1 :])
        keys[(airframe, day)] = read_key_file(path, exact=True)
    return keys
