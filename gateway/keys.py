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
from gateway.tunnel import derive_day_key

__all__ = ["load_day_keys", "read_credential", "read_key_file", "write_day_keys"]


def _problem(path: Path, message: str) -> ConfigError:
    return ConfigError([ConfigIssue(str(path), None, "(key file)", message)])


def read_key_file(path: Path, *, min_bytes: int = 32, exact: bool = False) -> bytes:
    """Read a key from ``path``: raw bytes or hex text; refuse group/world-readable files."""
    try:
        info = path.stat()
        data = path.read_bytes()
    except OSError as exc:
        raise _problem(path, f"cannot read key file: {exc.strerror}") from exc
    if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise _problem(
            path, f"key file mode is {stat.S_IMODE(info.st_mode):o}; expected 600 or stricter"
        )
    text = data.strip()
    try:
        key = bytes.fromhex(text.decode("ascii")) if text else b""
    except (UnicodeDecodeError, ValueError):
        key = data
    if len(key) < min_bytes or (exact and len(key) != min_bytes):
        wanted = f"exactly {min_bytes}" if exact else f"at least {min_bytes}"
        raise _problem(path, f"expected {wanted} key bytes, found {len(key)}")
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
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise _problem(path, f"cannot read credential: {exc.strerror}") from exc
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
