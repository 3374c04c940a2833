"""Every command survives a reader that closes stdout early (``fischer-gateway ... | head -1``).

stdout is the write end of a pipe whose read end is already closed, so the command's first
write fails with EPIPE for certain (a reader closing after one line races with a command
whose whole output fits in the pipe's buffer). The command ends quietly, status 0, with no
traceback and no "Exception ignored" from the flush at exit.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

HEAD = shutil.which("head") or "/usr/bin/head"


@pytest.mark.parametrize(
    "args",
    [
        ["selftest"],
        ["config-schema"],
        ["files", "example.yaml"],
    ],
    ids=lambda args: args[0],
)
def test_a_closed_stdout_ends_the_command_quietly(args: list[str]) -> None:
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        result = subprocess.run(
            [sys.executable, "-m", "gateway", *args],
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            timeout=60,
            check=False,
        )
    finally:
        os.close(write_end)
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""


def test_a_reader_that_stops_after_one_line_gets_that_line() -> None:
    """``fischer-gateway config-schema | head -1`` (119 kB of schema: more than a pipe holds)."""
    with subprocess.Popen(
        [sys.executable, "-m", "gateway", "config-schema"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    ) as gateway:
        assert gateway.stdout is not None
        head = subprocess.run(
            [HEAD, "-1"], stdin=gateway.stdout, capture_output=True, timeout=60, check=True
        )
        gateway.stdout.close()  # only head reads the pipe
        _, errors = gateway.communicate(timeout=60)
    assert head.stdout == b"{\n"
    assert gateway.returncode == 0, errors
    assert errors == b""
