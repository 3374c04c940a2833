"""Scale-out acceptance run: several ``fischer-gateway run`` nodes, one picture.

Reproducible: ``python bench/nats_nodes.py`` (``--help`` for options; the issue's run is the
default: 4 nodes, 1,000 airframes, a 60 s cut). Prints a Markdown table.

A hub node ``a`` aggregates ``--nodes - 1`` leaf nodes (``b``, ``c`` ...), each a
``fischer-gateway run`` with its own nats-server (JetStream in its own domain, random ports
on loopback); the airframes are spread over all nodes (sysids reused across nodes, at most
250 a node), each a simulated airframe reporting its state and ``--rounds`` detections. Then
leaf ``b``'s link to the hub is cut for ``--cut-s`` seconds while it keeps detecting, and
leaf ``c`` (with three nodes or more) is killed with SIGKILL just after a round of detections
and started again on its spool. The hub's picture (its jsonl archive) must hold every
airframe and every detection its leaves took in, once: lost and duplicated are counted.

The CI test of the same path, scaled down, is ``tests/e2e/test_nats_scale_out_run.py``.
"""

from __future__ import annotations

import argparse
import string
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
# Run as a script, bench/ is first on the path, and its nats.py would shadow the nats package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))
sys.path.append(str(_ROOT / "tests"))
sys.path.append(str(_ROOT / "tests" / "e2e"))

from daemon_support import Daemon, free_tcp_port, free_udp_port, wait_until  # noqa: E402
from nats_server import NatsServer, TcpCut  # noqa: E402
from test_nats_scale_out_run import Fleet, node_config, picture  # noqa: E402

MAX_PER_NODE = 250


def distinct_detections(archive: Path) -> dict[str, set[str]]:
    """Detection ids by airframe in an archive (a node's own archive may repeat after a kill)."""
    found: dict[str, set[str]] = {}
    for event in picture(archive):
        if event["kind"] == "detection":
            found.setdefault(event["airframe"], set()).add(event["event_id"])
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, default=4, help="gateway nodes, the hub included")
    parser.add_argument("--airframes", type=int, default=1000, help="spread over the nodes")
    parser.add_argument("--rounds", type=int, default=3, help="detections per airframe a phase")
    parser.add_argument("--cut-s", type=float, default=60.0, help="the leaf link cut")
    parser.add_argument("--timeout-s", type=float, default=300.0, help="per wait")
    args = parser.parse_args()
    if not 2 <= args.nodes <= 26:
        parser.error("--nodes: 2 to 26")
    per_node = -(-args.airframes // args.nodes)
    if per_node > MAX_PER_NODE:
        parser.error(f"--airframes: at most {MAX_PER_NODE} a node")
    names = list(string.ascii_lowercase[: args.nodes])
    hub_name, leaves = names[0], names[1:]
    counts = dict.fromkeys(names, per_node)
    counts[names[-1]] -= per_node * args.nodes - args.airframes
    ids = {name: [f"{name.upper()}-{n:03d}" for n in range(1, counts[name] + 1)] for name in names}
    timeline: list[tuple[str, float]] = []
    start = time.monotonic()

    def mark(what: str) -> None:
        timeline.append((what, time.monotonic() - start))
        print(f"{time.monotonic() - start:7.1f} s  {what}", file=sys.stderr)

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        leaf_port = free_tcp_port()
        with TcpCut(leaf_port) as link:
            hub_server = NatsServer(
                tmp, hub_name, hub=True, leaf_port=leaf_port, advertise=f"127.0.0.1:{link.port}"
            )
            servers = {hub_name: hub_server.start()}
            try:
                for leaf in leaves:
                    # Only b goes through the relay the run cuts.
                    port = link.port if leaf == "b" else leaf_port
                    servers[leaf] = NatsServer(
                        tmp, leaf, leaf_of=f"nats-leaf://127.0.0.1:{port}"
                    ).start()
                wait_until(
                    lambda: len(hub_server.leafz().get("leafs") or []) == len(leaves),
                    60,
                    "every leaf link",
                )
                udp = {name: free_udp_port() for name in names}
                configs, archives = {}, {}
                for name in names:
                    configs[name], archives[name] = node_config(
                        tmp,
                        name,
                        ids[name],
                        udp[name],
                        servers[name].url,
                        remotes=leaves if name == hub_name else None,
                    )
                fleets = {name: Fleet(udp[name], counts[name]) for name in names}
                daemons = {name: Daemon(configs[name]) for name in names}
                try:
                    mark("nodes up")
                    hub_archive = archives[hub_name]

                    def at_hub() -> dict[str, set[str]]:
                        return distinct_detections(hub_archive)

                    def settled() -> bool:
                        hub_has = at_hub()
                        for leaf in leaves:
                            for airframe, taken in distinct_detections(archives[leaf]).items():
                                if hub_has.get(airframe) != taken:
                                    return False
                        return all(len(hub_has.get(a, ())) >= args.rounds for a in ids[hub_name])

                    for fleet in fleets.values():
                        fleet.detect(args.rounds)
                    wait_until(settled, args.timeout_s, "every detection at the hub")
                    mark("every detection at the hub")

                    link.cut()
                    cut_at = time.monotonic()
                    mark(f"leaf b cut for {args.cut_s:g} s")
                    while time.monotonic() - cut_at < args.cut_s:
                        fleets["b"].detect(1)
                        time.sleep(min(5.0, max(0.0, args.cut_s - (time.monotonic() - cut_at))))
                    link.restore()
                    mark("leaf b restored")
                    wait_until(settled, args.timeout_s, "the cut's detections at the hub")
                    mark("leaf b caught up")

                    if "c" in leaves:
                        fleets["c"].detect(1)
                        daemons["c"].kill9()
                        mark("leaf c killed (SIGKILL)")
                        daemons["c"] = Daemon(configs["c"])
                        mark("leaf c running again")
                        wait_until(settled, args.timeout_s, "what c took in at the hub")
                        mark("leaf c caught up")
                    for fleet in fleets.values():
                        fleet.state()
                    everyone = {a for name in names for a in ids[name]}
                    wait_until(
                        lambda: (
                            {
                                e["airframe"]
                                for e in picture(hub_archive)
                                if e["kind"] == "telemetry"
                            }
                            >= everyone
                        ),
                        args.timeout_s,
                        "every airframe at the hub",
                    )
                    time.sleep(2.0)
                    mark("every airframe at the hub")
                    events = picture(hub_archive)
                finally:
                    for daemon in daemons.values():
                        daemon.stop()
                    for fleet in fleets.values():
                        fleet.sock.close()
                leaf_took = {
                    a: taken
                    for leaf in leaves
                    for a, taken in distinct_detections(archives[leaf]).items()
                }
            finally:
                for server in servers.values():
                    server.stop()
    detections = [e for e in events if e["kind"] == "detection"]
    by_id = Counter(e["event_id"] for e in detections)
    duplicated = sum(n - 1 for n in by_id.values() if n > 1)
    hub_ids = {e["event_id"] for e in detections}
    lost = sum(len(taken - hub_ids) for taken in leaf_took.values())
    airframes = {e["airframe"] for e in events if e["kind"] == "telemetry"}
    tracked = {a for e in events if e["kind"] == "track" for a in e["airframes"]}
    print(
        f"nats nodes: {args.nodes} nodes, {args.airframes} airframes, {args.rounds} rounds, "
        f"cut {args.cut_s:g} s\n"
    )
    print("| measure | value |")
    print("| --- | --- |")
    print(f"| airframes on the hub's picture | {len(airframes)} of {args.airframes} |")
    print(f"| detections at the hub | {len(detections)} ({len(hub_ids)} distinct) |")
    print(f"| leaves' detections lost at the hub | {lost} |")
    print(f"| duplicated at the hub | {duplicated} |")
    print(f"| airframes in the hub's tracks | {len(tracked)} |")
    for what, at in timeline:
        print(f"| {what} | {at:.1f} s |")
    if lost or duplicated or len(airframes) < args.airframes:
        sys.exit(1)


if __name__ == "__main__":
    main()
