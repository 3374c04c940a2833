"""``fischer-gateway order``'s own checks of its arguments (no daemon: nothing is sent)."""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import pytest

from gateway.ordercli import EXIT_UNREACHABLE, add_order_parser, order_command


def run(tmp_path: Path, *argv: str) -> tuple[int, str]:
    parser = argparse.ArgumentParser()
    add_order_parser(parser.add_subparsers(dest="command"))
    sock = tmp_path / "absent.sock"  # never connected to: every case here is refused first
    args = parser.parse_args(["order", "--socket", str(sock), *argv])
    out, err = io.StringIO(), io.StringIO()
    code = order_command(args, out, err)
    assert out.getvalue() == ""
    return code, err.getvalue()


@pytest.mark.parametrize(
    "where",
    [
        ("--polygon", "65.83,21.70", "65.83,21.72", "65.84,21.72"),
        ("--mgrs", "34WDU1234567890"),
    ],
)
def test_an_altitude_the_order_cannot_carry_is_refused_not_dropped(
    tmp_path: Path, where: tuple[str, ...]
) -> None:
    """The order format has an altitude on a point only: ``--alt-msl-m`` with an area or a
    grid reference would be dropped unsaid and the area flown at the current altitude."""
    code, err = run(tmp_path, "--task", "recon_area", *where, "--alt-msl-m", "320")
    assert code == EXIT_UNREACHABLE
    assert "--alt-msl-m is taken with --point only" in err


def test_a_point_with_an_altitude_goes_to_the_socket(tmp_path: Path) -> None:
    code, err = run(
        tmp_path, "--task", "observe_point", "--point", "65.84", "21.74", "--alt-msl-m", "320"
    )
    assert code == EXIT_UNREACHABLE
    assert "absent.sock" in err  # it got as far as connecting
