"""``fischer-gateway order``: an operator's five-line order to the running daemon.

Writes one order as a line of JSON (SLB's order format, ``slb-order.schema.json``) to the
``local`` order source's Unix socket and prints the JSON lines the daemon answers with:
``received``, then the orders processor's ``accepted`` or ``rejected`` (with the check and
its numbers) and, with ``--follow``, ``executing`` and ``completed`` or ``failed``. An order
whose airframe is not heard yet is answered ``waiting``: without ``--follow`` the command
returns then (exit 3; the daemon keeps the order until its window ends), with ``--follow``
it waits on, past ``--timeout``, for the answer the window's end brings at the latest. Exit
status: 0 when the order was accepted (with ``--follow``: completed), 1 when it was rejected,
failed or a conflict (its id was taken with other content), 2 when the daemon could not be
reached or did not answer within ``--timeout``, 3 when it waits for its airframe.
``--status ORDER_ID`` asks instead for every status the daemon keeps for an order (also those
that came while no client was connected, or before a restart), one JSON line each with its
``seq``; exit 0 if any is kept, 1 if none is.
Reconnaissance tasking only: the tasks are observe, track, survey and return.
"""

from __future__ import annotations

import argparse
import json
import math
import secrets
import socket
from datetime import UTC, datetime
from typing import Any, TextIO

__all__ = ["add_order_parser", "order_command"]

EXIT_OK, EXIT_REFUSED, EXIT_UNREACHABLE, EXIT_WAITING = 0, 1, 2, 3
_FINAL = {"rejected", "conflict", "completed", "failed", "not_held"}
_MAX_LINE = 65536


def _number(text: str) -> float:
    value = float(text)  # argparse reports a ValueError as an invalid value
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _corner(text: str) -> dict[str, float]:
    try:
        lat, lon = (_number(part) for part in text.split(","))
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"expected LAT,LON, got {text!r}") from None
    return {"lat_deg": lat, "lon_deg": lon}


def _when(text: str) -> str:
    try:
        moment = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an ISO 8601 time, got {text!r}") from None
    if moment.tzinfo is None:
        raise argparse.ArgumentTypeError(f"expected a time with a zone (Z, +01:00), got {text!r}")
    return moment.isoformat()


def add_order_parser(sub: Any) -> None:
    """Add the ``order`` command to the CLI's subparsers."""
    order = sub.add_parser(
        "order", help="send a reconnaissance order to the running daemon (local source)"
    )
    order.add_argument("--socket", required=True, help="the local source's Unix socket")
    order.add_argument(
        "--status",
        metavar="ORDER_ID",
        help="print every status kept for this order (no order is sent)",
    )
    order.add_argument(
        "--task",
        help="required unless --status",
        choices=["observe_point", "track_target", "recon_area", "return_to_base"],
    )
    where = order.add_mutually_exclusive_group()
    where.add_argument("--point", nargs=2, type=_number, metavar=("LAT", "LON"))
    where.add_argument("--mgrs", help="an MGRS reference, 1/10/100 m")
    where.add_argument("--polygon", nargs="+", type=_corner, metavar="LAT,LON")
    order.add_argument("--alt-msl-m", type=_number, help="commanded altitude (with --point only)")
    order.add_argument("--airframe", help="the airframe tasked; default: any suitable")
    order.add_argument("--order-id", help="default: op-<random>")
    order.add_argument("--issuer", default="local operator")
    order.add_argument(
        "--priority", default="priority", choices=["flash", "immediate", "priority", "routine"]
    )
    order.add_argument("--target", help="line 4: what to observe or track")
    order.add_argument(
        "--track-id", help="track_target: a live fused track to fly to (its newest position)"
    )
    order.add_argument(
        "--not-before", type=_when, metavar="TIME", help="line 3: start, ISO 8601 with a zone"
    )
    order.add_argument(
        "--not-after", type=_when, metavar="TIME", help="line 3: end, ISO 8601 with a zone"
    )
    order.add_argument(
        "--follow", action="store_true", help="wait until the order completed or failed"
    )
    order.add_argument("--timeout", type=float, default=30.0, help="seconds to wait per answer")


def _document(args: argparse.Namespace) -> dict[str, Any]:
    location: dict[str, Any]
    if args.point is not None:
        point = {"lat_deg": args.point[0], "lon_deg": args.point[1]}
        if args.alt_msl_m is not None:
            point["alt_msl_m"] = args.alt_msl_m
        location = {"point": point}
    elif args.mgrs is not None:
        location = {"mgrs": args.mgrs}
    else:
        location = {"polygon": args.polygon}
    stamp = datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    document: dict[str, Any] = {
        "order_id": args.order_id or f"op-{secrets.token_hex(4)}",
        "issuer": args.issuer,
        "issued": stamp,
        "task": args.task,
        "location": location,
        "priority": args.priority,
    }
    if args.airframe:
        document["airframe"] = args.airframe
    if args.target:
        document["target"] = args.target
    for key in ("track_id", "not_before", "not_after"):
        if getattr(args, key):
            document[key] = getattr(args, key)
    return document


def order_command(args: argparse.Namespace, out: TextIO, err: TextIO) -> int:
    """Run ``fischer-gateway order``; the exit status (see the module docstring)."""
    if args.status is not None:
        return _status_of(args, out, err)
    if args.task is None or (args.point, args.mgrs, args.polygon) == (None, None, None):
        print("order: --task and one of --point, --mgrs, --polygon are required", file=err)
        return EXIT_UNREACHABLE
    if args.alt_msl_m is not None and args.point is None:
        # The order format carries an altitude on a point only: dropping it unsaid would fly
        # the area or grid reference at the airframe's current altitude.
        print(
            "order: --alt-msl-m is taken with --point only; an --mgrs or --polygon order is "
            "flown at the airframe's current altitude",
            file=err,
        )
        return EXIT_UNREACHABLE
    document = _document(args)
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(args.timeout)
            sock.connect(str(args.socket))
            sock.sendall(json.dumps(document).encode() + b"\n")
            reader = sock.makefile("rb")
            while True:
                raw = reader.readline(_MAX_LINE)
                if not raw:
                    print(f"{args.socket}: the daemon closed the connection", file=err)
                    return EXIT_UNREACHABLE
                line = json.loads(raw)
                print(json.dumps(line), file=out, flush=True)
                status = line.get("status")
                if status in _FINAL:
                    return EXIT_OK if status == "completed" else EXIT_REFUSED
                if status == "accepted" and not args.follow:
                    return EXIT_OK
                if status == "waiting":
                    if not args.follow:
                        return EXIT_WAITING
                    sock.settimeout(None)  # the order's window ends it, not --timeout
    except TimeoutError:
        print(f"{args.socket}: no answer within {args.timeout} s", file=err)
        return EXIT_UNREACHABLE
    except (OSError, ValueError) as exc:
        print(f"{args.socket}: {exc}", file=err)
        return EXIT_UNREACHABLE


def _status_of(args: argparse.Namespace, out: TextIO, err: TextIO) -> int:
    """``--status ORDER_ID``: print the statuses the daemon keeps for the order."""
    lines = 0
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(args.timeout)
            sock.connect(str(args.socket))
            sock.sendall(json.dumps({"status_of": args.status}).encode() + b"\n")
            reader = sock.makefile("rb")
            while raw := reader.readline(_MAX_LINE):
                line = json.loads(raw)
                print(json.dumps(line), file=out, flush=True)
                if line.get("status") in ("unknown", "rejected"):
                    return EXIT_REFUSED
                lines += 1
    except TimeoutError:
        print(f"{args.socket}: no answer within {args.timeout} s", file=err)
        return EXIT_UNREACHABLE
    except (OSError, ValueError) as exc:
        print(f"{args.socket}: {exc}", file=err)
        return EXIT_UNREACHABLE
    return EXIT_OK if lines else EXIT_REFUSED
