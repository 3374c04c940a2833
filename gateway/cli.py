"""The ``fischer-gateway`` command: run, demo, check-config, config-schema, replay, simulate,
score, keys, selftest and files.

This is the only module that configures logging. Exit codes: 0 success, 1 runtime failure
(a link that cannot be opened, ...), 2 a config error (systemd does not restart on it).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import secrets
import select
import signal
import sys
from collections.abc import Callable, Coroutine, Sequence
from datetime import date, timedelta
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import anyio
import anyio.to_thread
import structlog

from gateway.app import Gateway
from gateway.c2.plugins import (
    PROCESSOR_GROUP,
    SOURCE_GROUP,
    check_sink,
    load_component,
    load_plugin,
)
from gateway.clock import utc_now
from gateway.configcheck import NodeCheck
from gateway.configfile import load_config
from gateway.errors import ConfigError, ConfigIssue, GatewayError
from gateway.fleet.hopdialect import HOP_RESULT_NAMES
from gateway.fleet.security.keys import load_day_keys, read_key_file, write_day_keys
from gateway.fleet.security.tunnel import DayKeys, Sealer
from gateway.ops.gcsetup import settle_gc
from gateway.ops.logsetup import configure_logging, install_loop_exception_handler
from gateway.ops.version import package_version
from gateway.ordercli import add_order_parser, order_command
from gateway.transports.listener import raise_open_files_limit

if TYPE_CHECKING:
    from gateway.sim.airframe import SimulatedAirframe
    from gateway.sim.resend import ResendPolicy
    from gateway.sim.runner import PlayStats
    from gateway.sim.scenario import Scenario

__all__ = ["main"]

log = structlog.get_logger(__name__)

EXIT_OK, EXIT_FAILURE, EXIT_CONFIG = 0, 1, 2
#: ``simulate --hop-result`` names: FISCHER_HOP_SCHEDULE_RESULT values.
_HOP_RESULTS = {name: value for value, name in HOP_RESULT_NAMES.items()}
#: MAVLink system ids are 8 bits and 0 is broadcast; every airframe needs its own.
MAX_AIRFRAMES = 255


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def _airframes(text: str) -> int:
    if not (text.isascii() and text.isdigit() and 1 <= int(text) <= MAX_AIRFRAMES):
        raise argparse.ArgumentTypeError(
            f"expected 1..{MAX_AIRFRAMES} (each airframe needs its own 8-bit MAVLink system "
            f"id, 0 is broadcast), got {text!r}"
        )
    return int(text)


def _port(text: str) -> int:
    if not (text.isascii() and text.isdigit() and int(text) <= 65535):
        raise argparse.ArgumentTypeError(f"expected a port 0..65535, got {text!r}")
    return int(text)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fischer-gateway",
        description="Gateway between the Fischer 26E fleet and C2 systems.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run the daemon")
    run.add_argument("--config", type=Path, required=True, help="YAML config file")
    demo = sub.add_parser(
        "demo", help="the brigade operation end to end: simulator, gateway, GUTE II, ATAK"
    )
    demo.add_argument("--duration", type=_positive, default=None, help="stop after S seconds")
    demo.add_argument(
        "--speed", type=_positive, default=1.0, help="play the scenario X times faster"
    )
    demo.add_argument("--udp-port", type=_port, default=None, help="override the demo's UDP port")
    demo.add_argument("--health-port", type=_port, default=None, help="override the health port")
    demo.add_argument("--archive", type=Path, default=None, help="where the JSONL archive goes")
    check = sub.add_parser("check-config", help="validate a config file; exit 2 on errors")
    check.add_argument("file", type=Path, nargs="?", help="YAML config file")
    check.add_argument(
        "--config", type=Path, dest="config_file", help="the same, spelled as for run"
    )
    check.add_argument(
        "--no-environment",
        action="store_true",
        help="check the file alone: no key files, credentials, devices, DEMs or sink files "
        "(for a config checked away from the node it will run on)",
    )
    sub.add_parser("config-schema", help="print the JSON Schema of the config")
    sub.add_parser("selftest", help="compute every claim of the ledger; exit 1 on a mismatch")
    replay = sub.add_parser("replay", help="send a .tlog to a gateway as an airframe would")
    replay.add_argument("file", type=Path)
    replay.add_argument("--to", required=True, help="udp://HOST:PORT")
    pace = replay.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=_positive, default=1.0, help="recorded speed times X")
    pace.add_argument("--fast", action="store_true", help="as fast as possible")
    replay.add_argument(
        "--progress-s", type=_positive, default=10.0, help="log progress every S seconds"
    )
    simulate = sub.add_parser("simulate", help="simulated airframes sending to a gateway")
    simulate.add_argument("--to", required=True, help="udp://HOST:PORT")
    simulate.add_argument(
        "--airframes", type=_airframes, default=None, help="1..255 (default 2; not with --scenario)"
    )
    simulate.add_argument("--duration", type=_positive, default=None, help="seconds (of sim time)")
    simulate.add_argument(
        "--scenario",
        default=None,
        help="a scenario YAML file, or a shipped one by name (brigade, crossing-columns, "
        "danger-close, loitering-munitions, parked-vehicles, shared-target, swarm, t72-column)",
    )
    simulate.add_argument(
        "--cot", default=None, help="udp://HOST:PORT of the gateway's CoT source (friendly units)"
    )
    simulate.add_argument(
        "--truth",
        type=Path,
        default=None,
        metavar="FILE",
        help="write the scenario's ground truth (every target each second, JSON lines; "
        "docs/tracking.md) to FILE as the run starts",
    )
    simulate.add_argument(
        "--speed",
        type=_positive,
        default=1.0,
        help="sim time runs X times real; targets then appear X times faster, so the "
        "gateway's fusion processor needs options: {speed_scale: X} (the demo sets it)",
    )
    simulate.add_argument(
        "--no-resend",
        action="store_true",
        help="never re-send a detection (for a gateway that does not acknowledge them)",
    )
    simulate.add_argument(
        "--resend-first",
        type=_positive,
        default=1.0,
        metavar="S",
        help="first re-send of an unacknowledged detection after S seconds (default 1)",
    )
    simulate.add_argument(
        "--resend-max",
        type=_positive,
        default=8.0,
        metavar="S",
        help="the re-send interval doubles up to S seconds (default 8)",
    )
    simulate.add_argument(
        "--resend-rate",
        type=_positive,
        default=20.0,
        metavar="HZ",
        help="at most HZ re-sends a second per airframe (default 20)",
    )
    simulate.add_argument(
        "--resend-before-ack",
        action="store_true",
        help="re-send even before the gateway has acknowledged any detection (one without "
        "acknowledgements then receives every detection several times)",
    )
    simulate.add_argument(
        "--linger",
        type=_non_negative,
        default=2.0,
        metavar="S",
        help="after --duration, wait up to S seconds for the last acknowledgements (default 2)",
    )
    simulate.add_argument(
        "--hop-result",
        choices=sorted(_HOP_RESULTS),
        default=None,
        help="answer every hop schedule with this result (default: accepted if the simulated "
        "radio can fly it)",
    )
    simulate.add_argument(
        "--autopilot",
        choices=("px4", "ardupilot", "arducopter"),
        default=None,
        help="whose HEARTBEAT, modes and command answers the airframes give (default "
        "ardupilot, ArduPlane; a scenario names each airframe's)",
    )
    simulate.add_argument(
        "--hop-ignore",
        type=int,
        default=0,
        metavar="N",
        help="leave the first N hop schedules unanswered, as a lost uplink would (default 0)",
    )
    for sub_parser in (replay, simulate):
        sub_parser.add_argument(
            "--key-dir", type=Path, default=None, help="day keys: seal frames in the tunnel"
        )
        sub_parser.add_argument(
            "--airframe-id",
            action="append",
            default=None,
            help="airframe id(s) whose day keys seal the frames (one per simulated airframe)",
        )
    scorer = sub.add_parser(
        "score", help="score the tracks of a JSONL archive against a truth file (GOSPA, ...)"
    )
    scorer.add_argument("--truth", type=Path, required=True, help="from simulate --truth")
    scorer.add_argument(
        "--tracks",
        type=Path,
        action="append",
        required=True,
        help="a JSONL archive (repeat for rotated files, oldest first)",
    )
    scorer.add_argument("--c", type=_positive, default=100.0, help="GOSPA cutoff, m (100)")
    scorer.add_argument("--p", type=_positive, default=2.0, help="GOSPA order, >= 1 (2)")
    scorer.add_argument(
        "--max-age",
        type=_positive,
        default=30.0,
        metavar="S",
        help="a track without a report for S seconds leaves the picture (30)",
    )
    scorer.add_argument("--json", action="store_true", help="one JSON object instead of text")
    spool = sub.add_parser("spool", help="look into the spool; list and re-queue dead letters")
    spool_sub = spool.add_subparsers(dest="spool_command", required=True)
    spool_status = spool_sub.add_parser("status", help="size, events owed per sink, dead letters")
    letters = spool_sub.add_parser("dead-letters", help="list dead letters, newest first")
    letters.add_argument("--sink", default=None, help="only this sink's")
    letters.add_argument("--limit", type=int, default=100, help="at most N (default 100)")
    letters.add_argument("--json", action="store_true", help="one JSON object per line")
    show = spool_sub.add_parser("show", help="print one dead letter's event as JSON")
    show.add_argument("id", type=int)
    requeue = spool_sub.add_parser("requeue", help="put dead letters back in their sink's queue")
    requeue.add_argument("ids", type=int, nargs="*", help="dead letter ids (see dead-letters)")
    requeue.add_argument("--all", action="store_true", help="every dead letter (of --sink)")
    requeue.add_argument("--sink", default=None, help="only this sink's")
    for spool_parser in (spool_status, letters, show, requeue):
        spool_parser.add_argument(
            "--config", type=Path, required=True, help="the gateway's config file (spool.path)"
        )
    keys = sub.add_parser("keys", help="tunnel key material")
    keys_sub = keys.add_subparsers(dest="keys_command", required=True)
    new = keys_sub.add_parser("new", help="write a new random master key (mode 0600)")
    new.add_argument("--out", type=Path, required=True)
    derive = keys_sub.add_parser("derive", help="an airframe's day keys, never the master")
    derive.add_argument("--master", type=Path, required=True, help="master key file")
    derive.add_argument("--airframe", required=True, type=_airframe_id)
    derive.add_argument("--from", dest="first", type=date.fromisoformat, required=True)
    derive.add_argument("--days", type=int, default=30)
    derive.add_argument("--out", type=Path, required=True, help="directory for the day keys")
    add_order_parser(sub)
    shipped = sub.add_parser("files", help="list, print or write the shipped config, unit, docs")
    shipped.add_argument("name", nargs="?", help="print this file")
    shipped.add_argument("--out", type=Path, default=None, help="write every file to DIR")
    return parser


def _udp_target(text: str, option: str = "--to") -> tuple[str, int]:
    from gateway.fleet.tlog import parse_udp_target

    try:
        return parse_udp_target(text)
    except ValueError as exc:
        raise ConfigError([ConfigIssue("(command line)", None, option, str(exc))]) from exc


def _usage_error(option: str, message: str) -> ConfigError:
    return ConfigError([ConfigIssue("(command line)", None, option, message)])


def _sealers(args: argparse.Namespace, count: int) -> list[Sealer | None]:
    if args.key_dir is None:
        return [None] * count
    ids = args.airframe_id or []
    if len(ids) != count:
        raise ConfigError(
            [
                ConfigIssue(
                    "(command line)",
                    None,
                    "--airframe-id",
                    f"--key-dir needs {count} --airframe-id value(s), found {len(ids)}",
                )
            ]
        )
    today = utc_now().date()
    sealers: list[Sealer | None] = []
    for airframe in ids:
        keys = load_day_keys(args.key_dir, airframe)
        if (airframe, today) not in keys:
            days = sorted(day for _, day in keys)
            held = f"{days[0]} .. {days[-1]}" if days else "none"
            raise ConfigError(
                [
                    ConfigIssue(
                        "(command line)",
                        None,
                        "--key-dir",
                        f"no day key for {airframe} today ({today}) in {args.key_dir} (it "
                        f"holds {held}); derive keys from today: fischer-gateway keys derive "
                        f"--airframe {airframe} --from {today} ...",
                    )
                ]
            )
        sealers.append(Sealer(airframe, DayKeys(keys=keys), utc_now))
    return sealers


def _airframe_id(text: str) -> str:
    """An airframe id as the config allows it (also a safe file-name part)."""
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", text):
        raise argparse.ArgumentTypeError(
            f"expected an airframe id as in the config (letters, digits, _ . -), found {text!r}"
        )
    return text


def _keys(args: argparse.Namespace) -> int:
    if args.keys_command == "new":
        fd = os.open(args.out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as handle:
            handle.write(secrets.token_hex(32) + "\n")
        print(f"wrote a new master key to {args.out} (mode 600)")  # noqa: T201 - the output
        return EXIT_OK
    if args.days < 1:
        print("--days must be at least 1", file=sys.stderr)  # noqa: T201 - the output
        return EXIT_CONFIG
    master = read_key_file(args.master)
    written = write_day_keys(master, args.airframe, args.first, args.days, args.out)
    print(  # noqa: T201 - the output
        f"wrote {len(written)} day keys for {args.airframe} to {args.out} "
        f"({args.first} .. {args.first + timedelta(days=args.days - 1)})"
    )
    return EXIT_OK


def _print_config_error(exc: ConfigError, stream: TextIO) -> None:
    for issue in exc.issues:
        print(issue, file=stream)
    print(f"{len(exc.issues)} error(s)", file=stream)


def _check_config(path: Path, *, environment: bool) -> int:
    warnings: list[ConfigIssue] = []
    node = NodeCheck(environment=environment)
    try:
        config = load_config(path, check_sink=check_sink, extra=node, warnings=warnings)
    except ConfigError as exc:
        _print_config_error(exc, sys.stderr)
        for warning in warnings:
            print(f"{warning} (warning)", file=sys.stderr)  # noqa: T201 - the output
        return EXIT_CONFIG
    for warning in warnings:
        print(f"{warning} (warning)", file=sys.stderr)  # noqa: T201 - the output
    out = sys.stdout
    scope = "" if environment else ", file only: --no-environment"
    summary = f"{len(config.airframes)} airframes, {len(config.sinks)} sinks{scope}"
    print(f"{path}: ok ({summary})", file=out)
    for entry in config.sinks:
        plugin = load_plugin(entry.type)
        print(
            f"  sink {entry.name}: type {entry.type} from {plugin.distribution} {plugin.version}",
            file=out,
        )
    for group, entries in (
        (PROCESSOR_GROUP, [(p.name, p.type) for p in config.processors]),
        (SOURCE_GROUP, [(s.name, s.type) for s in config.sources]),
    ):
        what = "processor" if group == PROCESSOR_GROUP else "source"
        for name, type_name in entries:
            component = load_component(group, type_name)
            print(
                f"  {what} {name}: type {type_name} from {component.distribution} "
                f"{component.version}",
                file=out,
            )
    return EXIT_OK


async def _serve(
    gateway: Gateway,
    duration_s: float | None,
    extra: Callable[[], Coroutine[Any, Any, None]] | None = None,
    config_path: Path | None = None,
) -> None:
    from gateway.reload import recheck_config

    install_loop_exception_handler()
    # SIGHUP (systemctl reload) re-checks the config file; without one, its default stands.
    wanted = (signal.SIGTERM, signal.SIGINT) + ((signal.SIGHUP,) if config_path else ())
    async with anyio.create_task_group() as tg:

        async def on_signal() -> None:
            with anyio.open_signal_receiver(*wanted) as signals:
                async for signum in signals:
                    log.info("signal_received", signal=signal.Signals(signum).name)
                    if signum == signal.SIGHUP and config_path is not None:
                        await recheck_config(config_path, gateway.config)
                    else:
                        gateway.shutdown()

        async def stop_after(delay_s: float) -> None:
            await anyio.sleep(delay_s)
            gateway.shutdown()

        tg.start_soon(on_signal)
        await tg.start(gateway.run)
        if extra is not None:
            tg.start_soon(extra)
        if duration_s is not None:
            tg.start_soon(stop_after, duration_s)
        await gateway.stopped.wait()
        tg.cancel_scope.cancel()


def _run_async(fn: Any, *args: Any) -> None:
    try:
        import uvloop  # noqa: F401 - optional speed-up, absent on some platforms

        options: dict[str, Any] = {"use_uvloop": True}
    except ImportError:
        options = {}
    anyio.run(fn, *args, backend="asyncio", backend_options=options)


def _demo(args: argparse.Namespace) -> int:
    from gateway.demo import prepare_demo

    demo = prepare_demo(
        args.archive, udp_port=args.udp_port, health_port=args.health_port, speed=args.speed
    )
    gateway = Gateway(demo.config, sinks=demo.sinks, source="demo.yaml")
    _run_async(_serve, gateway, args.duration, demo.player(gateway))
    return EXIT_OK


def _replay(args: argparse.Namespace) -> int:
    from gateway.fleet.tlog import ReplayStats, replay_udp

    host, port = _udp_target(args.to)
    if not args.file.is_file():
        raise ConfigError(
            [ConfigIssue(str(args.file), None, "(file)", "no such .tlog file (or not a file)")]
        )
    speed = None if args.fast else args.speed
    (sealer,) = _sealers(args, 1) if args.key_dir else (None,)
    seal = sealer.seal if sealer else None
    stats = ReplayStats()
    anyio.run(
        lambda: replay_udp(
            args.file,
            host,
            port,
            speed=speed,
            seal=seal,
            progress_interval_s=args.progress_s,
            stats=stats,
        )
    )
    if stats.refused:
        log.error(
            "replay_unheard",
            file=str(args.file),
            target=args.to,
            frames_sent=stats.sent,
            refused=stats.refused,
            reason="ICMP port unreachable: nothing listened for part or all of the replay",
        )
        return EXIT_FAILURE
    log.info("replay_finished", file=str(args.file), frames=stats.sent)
    return EXIT_OK


def _resend_policy(args: argparse.Namespace) -> ResendPolicy | None:
    from gateway.sim.resend import ResendPolicy

    if args.no_resend:
        return None
    if args.resend_max < args.resend_first:
        raise _usage_error(
            "--resend-max",
            f"expected at least --resend-first ({args.resend_first:g}), got {args.resend_max:g}",
        )
    return ResendPolicy(
        first_s=args.resend_first,
        max_s=args.resend_max,
        rate_hz=args.resend_rate,
        needs_ack_heard=not args.resend_before_ack,
    )


def _print_summaries(airframes: dict[str, SimulatedAirframe]) -> None:
    """One line per airframe on stdout: what became of its detections (and, for one that
    received hop schedules or was tasked, a line on each)."""
    for name, airframe in airframes.items():
        print(f"{name} (sysid {airframe.sysid}): {airframe.summary()}")  # noqa: T201 - the output
        tasked = airframe.autopilot_summary()
        if tasked is not None:
            print(f"{name} (sysid {airframe.sysid}): {tasked}")  # noqa: T201 - the output
        radio = airframe.radio
        if radio.schedules:
            print(  # noqa: T201 - the output
                f"{name} (sysid {airframe.sysid}): hop schedules received "
                f"{len(radio.schedules)}, active {radio.active_id:08x}, hop reports "
                f"{radio.reports}"
            )


def _simulate(args: argparse.Namespace) -> int:
    from gateway.sim.demofleet import build_demo_fleet, run_fleet

    host, port = _udp_target(args.to)
    if args.scenario is not None:
        return _simulate_scenario(args, host, port)
    if args.cot is not None:
        raise _usage_error("--cot", "friendly units come from a scenario: add --scenario")
    if args.truth is not None:
        raise _usage_error("--truth", "ground truth comes from a scenario: add --scenario")
    fleet = build_demo_fleet(
        args.airframes or 2, resend=_resend_policy(args), autopilot=args.autopilot or "ardupilot"
    )
    if args.hop_ignore < 0:
        raise _usage_error("--hop-ignore", f"expected 0 or more, got {args.hop_ignore}")
    for airframe in fleet:
        airframe.radio.ignore_first = args.hop_ignore
        if args.hop_result is not None:
            airframe.radio.result = _HOP_RESULTS[args.hop_result]
    sealers = _sealers(args, len(fleet))
    try:
        _run_async(
            lambda: run_fleet(
                fleet,
                host,
                [port] * len(fleet),
                duration_s=args.duration,
                speed=args.speed,
                sealers=sealers,
                linger_s=args.linger,
            )
        )
    finally:
        _print_summaries({f"airframe {a.sysid}": a for a in fleet})
    return EXIT_OK


def _simulate_scenario(args: argparse.Namespace, host: str, port: int) -> int:
    from gateway.sim.runner import PlayStats, play_scenario
    from gateway.sim.scenario import load_scenario

    if args.airframes is not None:
        raise _usage_error("--airframes", "the scenario names its airframes; drop --airframes")
    if args.hop_result is not None or args.hop_ignore:
        option = "--hop-result" if args.hop_result is not None else "--hop-ignore"
        raise _usage_error(option, "applies to the demo fleet, not to a --scenario")
    if args.autopilot is not None:
        raise _usage_error("--autopilot", "the scenario names each airframe's autopilot")
    scenario = load_scenario(args.scenario)
    cot = _udp_target(args.cot, "--cot") if args.cot is not None else None
    if cot is None and scenario.blue_forces:
        log.warning(
            "blue_forces_skipped",
            scenario=scenario.name,
            units=len(scenario.blue_forces),
            reason="no --cot: friendly units are sent to the gateway's CoT source",
        )
    if args.key_dir is not None and args.airframe_id is None:
        args.airframe_id = [airframe.id for airframe in scenario.airframes]
    sealers = _sealers(args, len(scenario.airframes))
    resend = _resend_policy(args)
    stats = PlayStats()
    log.info(
        "scenario_started",
        scenario=scenario.name,
        airframes=len(scenario.airframes),
        duration_s=args.duration or scenario.duration_s,
        speed=args.speed,
    )
    play = partial(
        play_scenario,
        scenario,
        host,
        port,
        cot=cot,
        duration_s=args.duration,
        speed=args.speed,
        sealers=sealers,
        stats=stats,
        resend=resend,
        linger_s=args.linger,
    )
    # Opened before the run, so a path that cannot be written fails before anything is sent.
    truth = args.truth.open("w", encoding="utf-8") if args.truth is not None else None
    try:
        _run_async(_play_with_truth, play, truth, scenario, args, stats)
    finally:
        if truth is not None:
            truth.close()
        _print_summaries(stats.airframes)
    log.info(
        "scenario_finished",
        scenario=scenario.name,
        frames=stats.frames,
        detections=stats.detections,
        blue_force_reports=stats.reports,
        blue_force_reports_refused=stats.reports_refused,
    )
    return EXIT_OK


async def _play_with_truth(
    play: Callable[..., Coroutine[Any, Any, Any]],
    truth: TextIO | None,
    scenario: Scenario,
    args: argparse.Namespace,
    stats: PlayStats,
) -> None:
    """Run ``play``; once its airframes have started, write the truth on their clock."""
    from gateway.sim.truth import write_truth

    async with anyio.create_task_group() as tg:
        await tg.start(play)
        if truth is None:
            return
        start = min(flyer.boot_unix_s for flyer in stats.airframes.values())
        records = await anyio.to_thread.run_sync(
            partial(
                write_truth,
                truth,
                scenario,
                start,
                speed=args.speed,
                duration_s=args.duration,
            )
        )
        truth.flush()
        log.info("truth_written", file=str(args.truth), records=records)


def _score(args: argparse.Namespace) -> int:
    from gateway.errors import ScoreInputError
    from gateway.scoring.files import read_archive, read_truth
    from gateway.scoring.report import score_json, score_text
    from gateway.scoring.score import ScoreSettings, score

    if args.p < 1:
        print(f"--p: expected a number >= 1, got {args.p:g}", file=sys.stderr)  # noqa: T201
        return EXIT_CONFIG
    try:
        truth = read_truth(args.truth)
        tracks = read_archive(args.tracks, truth.plane)
    except ScoreInputError as exc:
        print(exc, file=sys.stderr)  # noqa: T201 - the output
        return EXIT_CONFIG
    result = score(truth, tracks, ScoreSettings(c_m=args.c, p=args.p, max_age_s=args.max_age))
    print(score_json(result) if args.json else score_text(result))  # noqa: T201 - the output
    return EXIT_OK


def _spool(args: argparse.Namespace) -> int:
    from gateway.errors import SpoolError
    from gateway.spool import admin
    from gateway.spool.store import Spool

    try:
        config = load_config(args.config, check_sink=None)
    except ConfigError as exc:
        _print_config_error(exc, sys.stderr)
        return EXIT_CONFIG
    path = config.spool.path
    if path is None:
        print(  # noqa: T201 - the output
            f"{args.config}: spool.path is not set; the spool is in the gateway's memory",
            file=sys.stderr,
        )
        return EXIT_CONFIG
    if not path.exists():
        hint = (
            ""
            if path.is_absolute()
            else " (spool.path is relative: the gateway resolves it from its working "
            "directory, /var/lib/fischer-gateway under systemd; run this from there)"
        )
        print(f"{path.absolute()}: no spool here{hint}", file=sys.stderr)  # noqa: T201
        return EXIT_FAILURE
    try:
        spool = Spool(
            path,
            exclusive=False,
            max_bytes=config.spool.max_bytes,
            dead_letters_max=config.spool.dead_letters_max,
        )
    except SpoolError as exc:
        print(exc, file=sys.stderr)  # noqa: T201 - the output
        return EXIT_FAILURE
    try:
        if args.spool_command == "status":
            return admin.status(spool, sys.stdout)
        if args.spool_command == "dead-letters":
            return admin.dead_letters(
                spool, sys.stdout, sink=args.sink, limit=args.limit, as_json=args.json
            )
        if args.spool_command == "show":
            return admin.show(spool, sys.stdout, sys.stderr, args.id)
        return admin.requeue(
            spool, sys.stdout, sys.stderr, args.ids, every=args.all, sink=args.sink
        )
    finally:
        spool.close()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``fischer-gateway`` console script.

    A reader that closes stdout early (``fischer-gateway selftest | head -1``) has what it
    wanted: the command ends quietly with status 0, stdout pointed at /dev/null so that
    nothing more (not even the flush at exit) fails. A broken pipe that is not stdout's (a
    peer's socket) is not mistaken for it.
    """
    try:
        code = _command(argv)
        sys.stdout.flush()  # a pipe closed after the last write fails here, not at exit
    except BrokenPipeError:
        if not _stdout_closed():
            raise
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return EXIT_OK
    return code


def _stdout_closed() -> bool:
    """True when stdout is a pipe or socket whose reader has gone (poll says POLLERR)."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(mask & (select.POLLERR | select.POLLHUP) for _, mask in poller.poll(0))
    except (OSError, ValueError):  # no file descriptor behind sys.stdout
        return False


def _command(argv: Sequence[str] | None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "config-schema":
        from gateway.configschema import config_schema

        print(json.dumps(config_schema(), indent=2))  # noqa: T201 - the output
        return EXIT_OK
    if args.command == "check-config":
        if (args.file is None) == (args.config_file is None):
            print(  # noqa: T201 - the command's answer
                "fischer-gateway check-config: give one config file, as FILE or --config FILE",
                file=sys.stderr,
            )
            return EXIT_CONFIG
        path = args.file if args.file is not None else args.config_file
        return _check_config(path, environment=not args.no_environment)
    if args.command == "files":
        from gateway.ops.share import files_command

        return files_command(args.name, args.out, sys.stdout, sys.stderr)
    if args.command == "selftest":
        from gateway.domain.selftest import run_selftest

        return run_selftest(sys.stdout)
    if args.command == "spool":
        return _spool(args)
    if args.command == "score":
        return _score(args)
    if args.command == "order":
        return order_command(args, sys.stdout, sys.stderr)
    if args.command == "keys":
        try:
            return _keys(args)
        except ConfigError as exc:
            _print_config_error(exc, sys.stderr)
            return EXIT_CONFIG
        except FileExistsError:
            print(f"{args.out} exists; not overwriting a key", file=sys.stderr)  # noqa: T201
            return EXIT_CONFIG
        except BrokenPipeError:
            raise  # main's: the key is written, its reader closed stdout
        except OSError as exc:
            where = exc.filename or args.out
            print(f"{where}: {exc.strerror or exc}", file=sys.stderr)  # noqa: T201
            return EXIT_CONFIG
    # Logs go to stderr for every command: stdout is for output (the console sink's events).
    configure_logging("info")
    try:
        if args.command == "run":
            node = NodeCheck(environment=True)
            warnings: list[ConfigIssue] = []
            config = load_config(args.config, check_sink=check_sink, extra=node, warnings=warnings)
            configure_logging(config.gateway.log_level)
            for warning in warnings:
                log.warning("config_warning", warning=str(warning))
            soft, _hard = raise_open_files_limit()
            log.info("open_files_limit", soft=soft)
            gateway = Gateway(config, sinks=node.sinks, source=str(args.config))
            frozen, threshold = settle_gc()  # freeze start-up, fewer young collections
            log.info("gc_settled", frozen_objects=frozen, threshold=list(threshold))
            _run_async(partial(_serve, config_path=args.config), gateway, None)
            return EXIT_OK
        if args.command == "demo":
            return _demo(args)
        if args.command == "replay":
            return _replay(args)
        return _simulate(args)
    except BrokenPipeError:
        raise  # main's: stdout closed by its reader, not the gateway's failure
    except Exception as exc:
        config_errors = [e for e in _leaves(exc) if isinstance(e, ConfigError)]
        # OSError: a port already in use, a file that cannot be opened: said plainly, exit 1.
        failures = [e for e in _leaves(exc) if isinstance(e, GatewayError | OSError)]
        for config_error in config_errors:
            _print_config_error(config_error, sys.stderr)
        if config_errors:
            return EXIT_CONFIG
        if not failures:
            raise
        for failure in failures:
            log.error(
                "gateway_failed",
                error=str(failure),
                type=type(failure).__name__,
                **_os_cause(failure),
            )
        return EXIT_FAILURE
    except KeyboardInterrupt:
        return EXIT_OK


def _os_cause(exc: BaseException) -> dict[str, Any]:
    """errno and strerror of the first OSError in ``exc``'s cause chain that has them.

    uvloop wraps a failed UDP bind as ``OSError("could not bind to local_addr ...")`` with
    no errno, the real ``[Errno 98] Address already in use`` only in ``__cause__``.
    """
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno is not None:
            return {"errno": seen.errno, "strerror": seen.strerror}
        seen = seen.__cause__ or seen.__context__
    return {}


def _leaves(exc: BaseException) -> list[BaseException]:
    """The exceptions inside (possibly nested) exception groups from task groups."""
    if isinstance(exc, BaseExceptionGroup):
        return [leaf for inner in exc.exceptions for leaf in _leaves(inner)]
    return [exc]
