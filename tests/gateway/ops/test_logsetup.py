"""Logging as journald and operators read it: priorities, no locals, asyncio's errors.

Each case runs in a fresh interpreter: ``configure_logging`` caches loggers process-wide,
which would leak into the other tests.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest


def run_logging(code: str, tmp_path: Path, *, journal: str | None = "match") -> list[str]:
    """Run ``code`` after ``configure_logging("debug", stream)`` with ``stream`` a file;
    return the file's lines. ``journal``: "match" sets JOURNAL_STREAM to that file's
    dev:inode, "other" to another file's, None leaves it unset."""
    out = tmp_path / "log.txt"
    other = tmp_path / "other.txt"
    other.touch()
    script = textwrap.dedent(
        """
        import os, sys
        import structlog
        from gateway.ops.logsetup import configure_logging, install_loop_exception_handler
        stream = open(sys.argv[1], "w", encoding="utf-8")
        env = dict(os.environ)
        if sys.argv[2] != "none":
            st = os.stat(sys.argv[1] if sys.argv[2] == "match" else sys.argv[3])
            env["JOURNAL_STREAM"] = f"{st.st_dev}:{st.st_ino}"
        configure_logging("debug", stream, env)
        log = structlog.get_logger("t")
        """
    ) + textwrap.dedent(code)
    env = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
    result = subprocess.run(
        [sys.executable, "-c", script, str(out), journal or "none", str(other)],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
        env=env,
    )
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""  # nothing bypasses structlog
    return out.read_text().splitlines()


class TestJournalPriority:
    """Under journald every JSON line starts with its syslog priority."""

    def test_each_level_gets_its_priority(self, tmp_path: Path) -> None:
        lines = run_logging(
            """
            log.debug("a"); log.info("b"); log.warning("c"); log.error("d")
            stream.flush()
            """,
            tmp_path,
        )
        assert [line[:3] for line in lines] == ["<7>", "<6>", "<4>", "<3>"]
        assert [json.loads(line[3:])["event"] for line in lines] == ["a", "b", "c", "d"]

    @pytest.mark.parametrize("journal", ["other", None])
    def test_no_prefix_when_the_stream_is_not_the_journal(
        self, tmp_path: Path, journal: str | None
    ) -> None:
        """A redirected stream inherits JOURNAL_STREAM but is not the journal."""
        lines = run_logging('log.warning("c"); stream.flush()', tmp_path, journal=journal)
        assert json.loads(lines[0])["event"] == "c"


@pytest.mark.parametrize("value", ["²:1", "1:²", "１:1", ":", "", "a:b"])
def test_a_journal_stream_variable_that_is_not_two_numbers_is_not_the_journal(
    tmp_path: Path, value: str
) -> None:
    """``str.isdigit`` takes "²" and full-width digits that ``int`` refuses: never a crash."""
    from gateway.ops.logsetup import is_journal_stream

    with (tmp_path / "log.txt").open("w", encoding="utf-8") as stream:
        assert is_journal_stream(stream, {"JOURNAL_STREAM": value}) is False


class TestTracebacks:
    """A traceback in a log record never carries local variables."""

    CODE = """
        def handle(payload):
            secret_key = "5ecret-" + "k3y"
            raise ValueError("bad frame")
        try:
            handle(b"payload-bytes")
        except ValueError:
            log.exception("frame_failed")
        stream.flush()
        """

    def test_json_tracebacks_have_frames_but_no_locals(self, tmp_path: Path) -> None:
        (line,) = run_logging(self.CODE, tmp_path, journal=None)
        record = json.loads(line)
        assert record["exception"][0]["exc_type"] == "ValueError"
        assert record["exception"][0]["frames"][-1]["name"] == "handle"
        assert "5ecret-k3y" not in line
        assert "payload-bytes" not in line
        assert "locals" not in json.dumps(record["exception"][0]["frames"])

    def test_console_tracebacks_have_no_locals(self, tmp_path: Path) -> None:
        code = (
            "import io\n"
            "class Tty(io.StringIO):\n"
            "    def isatty(self): return True\n"
            "tty = Tty()\n"
            "configure_logging('debug', tty, {})\n"
            "log = structlog.get_logger('t2')\n"
            + textwrap.dedent(self.CODE).replace("stream.flush()", "stream.write(tty.getvalue())")
        )
        text = "\n".join(run_logging(code, tmp_path, journal=None))
        assert "ValueError: bad frame" in text
        assert "5ecret-k3y" not in text


def test_asyncio_loop_errors_become_one_json_record(tmp_path: Path) -> None:
    """A failing loop callback is one ``asyncio_error`` line, not a multi-line traceback."""
    lines = run_logging(
        """
        import asyncio
        def callback():
            raise RuntimeError("flush failed")
        async def main():
            install_loop_exception_handler()
            done = asyncio.Event()
            asyncio.get_running_loop().call_soon(callback)
            asyncio.get_running_loop().call_soon(done.set)
            await done.wait()
        asyncio.run(main())
        stream.flush()
        """,
        tmp_path,
    )
    assert len(lines) == 1
    assert lines[0].startswith("<3>")
    record = json.loads(lines[0][3:])
    assert record["event"] == "asyncio_error"
    assert record["exception"][0]["exc_value"] == "flush failed"
    assert "callback" in record["handle"]


def test_a_repeated_loop_error_is_one_record_per_interval(tmp_path: Path) -> None:
    """A peer can make a library's callback fail once per connection: not a line each."""
    lines = run_logging(
        """
        import asyncio
        def callback():
            raise TimeoutError(110, "Connection timed out")
        def other():
            raise RuntimeError("flush failed")
        async def main():
            install_loop_exception_handler()
            done = asyncio.Event()
            loop = asyncio.get_running_loop()
            for _ in range(50):
                loop.call_soon(callback)
            loop.call_soon(other)
            loop.call_soon(done.set)
            await done.wait()
        asyncio.run(main())
        stream.flush()
        """,
        tmp_path,
    )
    records = [json.loads(line[3:]) for line in lines]
    assert [r["exception"][0]["exc_type"] for r in records] == ["TimeoutError", "RuntimeError"]
    assert all(r["event"] == "asyncio_error" for r in records)
