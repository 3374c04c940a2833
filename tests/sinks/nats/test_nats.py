"""The ``nats`` sink and source against real nats-servers on loopback (one per test).

Node ``b`` is a leaf of hub ``a``; each runs JetStream in its own domain. The sink on ``b``
publishes acked with the event id as ``Nats-Msg-Id``; the source on ``a`` consumes the
aggregate stream, marks each event with its origin and never takes one twice.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path

import anyio
import nats
import pytest
import trustme
from nats_server import DEBIAN_NATS_SERVER, NEEDS_DEBIAN_NATS, NEEDS_NATS, NatsServer
from pydantic import ValidationError

from gateway.contract import sample_events
from gateway.errors import TransientSinkError
from gateway.events import (
    Detection,
    Event,
    EventKind,
    Handoff,
    OrderStatus,
    Position,
    Sensor,
    Telemetry,
)
from gateway.spool.group import Commit
from sinks.nats.sink import NatsSink, NatsSinkConfig
from sinks.nats.source import NatsSource, NatsSourceConfig
from sinks.nats.streams import events_stream
from sinks.nats.subjects import BadMessage, airframe_token, decode_event, encode_event, subject_for

pytestmark = NEEDS_NATS

NOW = datetime(2026, 11, 27, 8, 0, 0, tzinfo=UTC)


def detection(airframe: str, n: int) -> Detection:
    return Detection(
        event_id=f"{airframe}-det-{n}-{1000 + n}",
        airframe=airframe,
        time=NOW,
        sensor=Sensor.EO,
        object_class="tank",
        confidence=0.9,
        position=Position(lat_deg=65.8, lon_deg=21.7),
        sigma_h_m=8.0,
    )


def test_airframe_ids_with_dots_and_wildcards_become_one_token() -> None:
    assert airframe_token("F26E-001") == "F26E-001"
    assert airframe_token("a.b*c >d_") == "a_2Eb_2Ac_20_3Ed_5F"
    long = airframe_token("x" * 300)
    assert len(long) <= 96
    assert long != airframe_token("x" * 299)
    assert subject_for("b", detection("F.1", 1)) == "fsg.b.det.F_2E1"


def test_a_message_is_refused_with_its_reason() -> None:
    event = detection("F1", 1)
    body = encode_event(event)
    assert decode_event("fsg.b.det.F1", body).origin_node == "b"
    for subject, data, reason in [
        ("fsg.b.tlm.F1", body, "carries a detection"),
        ("fsg.b.det.F2", body, "airframe"),
        ("fsg.b.trk.F1", body, "not carried"),
        ("fsg.b.det", body, "is not fsg"),
        ("fsg.b.det.F1", b"{", "not a valid event"),
        ("fsg.b.det.F1", b"x" * 70_000, "too large"),
        (
            "fsg.b.det.F1",
            event.model_copy(update={"event_id": "i" * 60_000}).model_dump_json().encode(),
            "longer than 256",
        ),
        (
            f"fsg.b.det.{airframe_token('A' * 300)}",
            event.model_copy(update={"airframe": "A" * 300}).model_dump_json().encode(),
            "longer than 256",
        ),
        (
            "fsg.b.det.F1",
            event.model_copy(update={"origin_node": "c"}).model_dump_json().encode(),
            "relayed",
        ),
    ]:
        with pytest.raises(BadMessage, match=reason):
            decode_event(subject, data)


def test_options_are_checked() -> None:
    with pytest.raises(ValidationError, match="node"):
        NatsSinkConfig(node="a.b")
    with pytest.raises(ValidationError, match="not carried"):
        NatsSinkConfig.model_validate({"node": "a", "kinds": ["track"]})
    with pytest.raises(ValidationError, match="nats://"):
        NatsSinkConfig(node="a", servers=["http://x"])
    with pytest.raises(ValidationError, match="named twice"):
        NatsSourceConfig(node="a", remotes=["b", "b"])
    with pytest.raises(ValidationError, match=r"remotes\n.*'a' is this node itself"):
        NatsSourceConfig(node="a", remotes=["b", "a"])
    with pytest.raises(ValidationError, match=r"node\n.*a node name is 1-32 letters"):
        NatsSinkConfig(node="b c")
    for key in ("creds_file", "token_file"):  # the error names the key (and so its line)
        with pytest.raises(ValidationError, match=rf"{key}\n.*no such file"):
            NatsSinkConfig.model_validate(
                {"node": "a", key: "/nonexistent.creds"}, context={"environment": True}
            )


HUB_CONFIG = """\
gateway: {node_id: a}
health: {enabled: false}
airframes:
  - id: A-001
    sysid: 1
    links: [{uri: "udp://127.0.0.1:0", security: unsecured}]
sources:
  - name: brigades
    type: nats
    node: a
    servers: ['nats://127.0.0.1:4222']
    remotes: [b]
sinks:
  - {name: archive, type: jsonl, options: {path: archive.jsonl}}
"""


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            "    remotes: [b]",
            "    remotes: [b]\n    creds_file: /nonexistent/nats.creds",
            ":13 sources[0].creds_file: no such file",
        ),
        (
            "nats://127.0.0.1:4222",
            "nats://127.0.0.1:notaport",
            ":11 sources[0].servers: 'nats://127.0.0.1:notaport': not a URL",
        ),
        ("nats://127.0.0.1:4222", "nats://", ":11 sources[0].servers: 'nats://': no host"),
        (
            "nats://127.0.0.1:4222",
            "nats://fg:hunter2@127.0.0.1:4222",
            ":11 sources[0].servers: a server URL carries no user or password",
        ),
        (
            "nats://127.0.0.1:4222",
            "htp:/127.0.0.1:x",
            ":11 sources[0].servers: 'htp:/127.0.0.1:x': a server URL starts with nats://",
        ),
        ("remotes: [b]", "remotes: [b, 'c.>']", ":12 sources[0].remotes: 'c.>': a node name"),
        ("remotes: [b]", "remotes: [b, a]", ":12 sources[0].remotes: 'a' is this node itself"),
        ("    node: a", "    node: a b", ":10 sources[0].node: a node name is 1-32"),
    ],
)
def test_run_refuses_a_bad_nats_config_naming_key_and_line(
    tmp_path: Path, old: str, new: str, message: str
) -> None:
    config = tmp_path / "hub.yaml"
    assert old in HUB_CONFIG
    config.write_text(HUB_CONFIG.replace(old, new))
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "run", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=tmp_path,
    )
    assert result.returncode == 2, result.stderr
    assert f"{config}{message}" in result.stderr
    assert "Traceback" not in result.stderr
    assert "hunter2" not in result.stderr


def test_check_config_warns_of_a_node_that_publishes_without_credentials(
    tmp_path: Path,
) -> None:
    open_sink = NatsSink("to-hub", NatsSinkConfig(node="b"))
    (warning,) = open_sink.environment_warnings()
    assert "no credentials" in warning
    assert "fsg.b.>" in warning
    token = tmp_path / "token"
    token.write_text("secret")
    closed = NatsSink("to-hub", NatsSinkConfig(node="b", token_file=token))
    assert closed.environment_warnings() == []


@pytest.fixture(
    params=[
        pytest.param(None, id="current"),
        pytest.param(DEBIAN_NATS_SERVER, id="debian-2.9", marks=NEEDS_DEBIAN_NATS),
    ]
)
def nodes(
    tmp_path: Path, request: pytest.FixtureRequest
) -> Iterator[tuple[NatsServer, NatsServer]]:
    binary = request.param
    hub = NatsServer(tmp_path, "a", hub=True, binary=binary)
    leaf = NatsServer(
        tmp_path, "b", leaf_of=f"nats-leaf://127.0.0.1:{hub.leaf_port}", binary=binary
    )
    with hub, leaf:
        deadline = time.monotonic() + 20
        while not hub.leafz().get("leafs") and time.monotonic() < deadline:
            time.sleep(0.02)
        yield hub, leaf


def test_the_sink_publishes_acked_once_and_the_source_takes_each_once(
    nodes: tuple[NatsServer, NatsServer],
) -> None:
    hub, leaf = nodes
    received: list[Event] = []
    refusals = [True]  # the bus refuses the first event once (a full spool): asked again

    def publish(event: Event) -> bool:
        if refusals:
            refusals.pop()
            return False
        received.append(event)
        return True

    async def main() -> NatsSink:
        sink = NatsSink("out", NatsSinkConfig(node="b", servers=[leaf.url]))
        await sink.open()
        batch: list[Event] = [detection("F.1", n) for n in range(50)]
        batch.append(Telemetry(event_id="t1", airframe="F.1", time=NOW))
        await sink.send(batch)
        await sink.send(batch[:10])  # a retried batch: the stream drops the repeats
        relayed = detection("R1", 1).model_copy(update={"origin_node": "c"})
        await sink.send([relayed])  # another node's: never published again
        # Hostile messages on node b's subjects: counted and dropped, never the end of it.
        raw = await nats.connect(leaf.url)
        good = encode_event(detection("F9", 9))
        for subject, body in [
            ("fsg.b.det.F1", b"{"),  # not JSON
            ("fsg.b.det.F1", good),  # another airframe than the subject names
            ("fsg.b.det.F9", encode_event(relayed)),  # already relayed
            # Another node's state of an airframe of the aggregating node's own: refused.
            ("fsg.b.tlm.OWN-1", encode_event(Telemetry(event_id="o", airframe="OWN-1", time=NOW))),
        ]:
            await raw.jetstream().publish(subject, body)
        await raw.close()
        source = NatsSource(
            "in",
            NatsSourceConfig(node="a", servers=[hub.url], remotes=["b"]),
            publish,
            clock=lambda: NOW,
        )
        source.set_own_airframes(frozenset({"OWN-1"}))
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            with anyio.fail_after(30):
                while len(received) < 51:  # noqa: ASYNC110 - polling what a callback appends
                    await anyio.sleep(0.05)
            await anyio.sleep(0.3)
            tg.cancel_scope.cancel()
        await sink.aclose()
        status = source.status()
        assert status["by_node"] == {"b": 51}
        assert status["counts"] == {
            "bad": 3,
            "own_airframe": 1,
            "refused": 1,
            "detection": 50,
            "telemetry": 1,
        }
        return sink

    sink = anyio.run(main)
    assert sink.counts() == {"published": 51, "duplicate": 10, "relayed_skipped": 1}
    assert len(received) == 51
    assert {e.origin_node for e in received} == {"b"}
    ids = [e.event_id for e in received if isinstance(e, Detection)]
    assert sorted(ids) == sorted(f"F.1-det-{n}-{1000 + n}" for n in range(50))


class Ledger:
    """The spool's part the source uses: a group that commits (or not) on flush, and the
    detection ids of committed groups."""

    def __init__(self, commits: list[bool]) -> None:
        self.commits = commits  # the outcome of each flush in turn; then True
        self.ids: set[str] = set()
        self._open: Commit | None = None
        self._new: set[str] = set()

    def group(self) -> Commit:
        if self._open is None:
            self._open = Commit()
        return self._open

    def flush(self) -> bool:
        group, self._open = self._open, None
        ok = self.commits.pop(0) if self.commits else True
        if ok:
            self.ids |= self._new
        self._new = set()
        if group is not None:
            group.end(ok)
        return ok

    def seen(self, event_id: str) -> bool:
        return event_id in self.ids or event_id in self._new

    def remember(self, event_id: str) -> None:
        self._new.add(event_id)


def test_acked_only_once_committed_and_a_replay_after_a_restart_is_dropped(
    nodes: tuple[NatsServer, NatsServer],
) -> None:
    """A batch whose spool group did not commit is asked again (nothing acked before the
    commit, so a kill -9 then loses nothing); a detection the spool holds already, sent
    again under another message id to a source started afresh, is a duplicate."""
    hub, leaf = nodes
    received: list[Event] = []
    ledger = Ledger([False])

    def publish(event: Event) -> bool:
        received.append(event)
        return True

    def source() -> NatsSource:
        # A pull request of the first source may outlive it and take a message the server
        # then holds for ack_wait: keep that short.
        built = NatsSource(
            "in",
            NatsSourceConfig(node="a", servers=[hub.url], remotes=["b"], ack_wait_s=1),
            publish,
            clock=lambda: NOW,
        )
        built.set_ledger(ledger)
        return built

    async def consume(built: NatsSource, until: Callable[[], bool]) -> None:
        async with anyio.create_task_group() as tg:
            await tg.start(built.run)
            with anyio.fail_after(30):
                while not until():  # noqa: ASYNC110 - polling what a callback appends
                    await anyio.sleep(0.05)
            await anyio.sleep(0.3)
            tg.cancel_scope.cancel()

    async def main() -> tuple[dict[str, object], dict[str, object]]:
        sink = NatsSink("out", NatsSinkConfig(node="b", servers=[leaf.url]))
        await sink.open()
        await sink.send([detection("F1", n) for n in range(5)])
        first = source()
        await consume(first, lambda: len(ledger.ids) == 5)
        # The hub restarts (a new source, the spool's ids kept); a replay of an old
        # detection under a new message id, then a new one.
        raw = await nats.connect(leaf.url)
        body = encode_event(detection("F1", 0))
        await raw.jetstream().publish("fsg.b.det.F1", body, headers={"Nats-Msg-Id": "again"})
        await raw.close()
        await sink.send([detection("F1", 5)])
        await sink.aclose()
        second = source()
        await consume(
            second,
            lambda: len(ledger.ids) == 6 and "duplicate" in second.status()["counts"],  # type: ignore[operator]
        )
        return first.status(), second.status()

    first, second = anyio.run(main)
    counts = first["counts"]
    assert isinstance(counts, dict)
    assert counts["detection"] == 5
    assert 1 <= counts["not_committed"] <= 5  # the first batch fetched: 1 to 5 messages
    assert second["counts"] == {"duplicate": 1, "detection": 1}
    # The first batch published twice (a group that did not commit undoes its events in the
    # spool), the rest once.
    assert len(received) == 5 + counts["not_committed"] + 1
    assert ledger.ids == {f"F1-det-{n}-{1000 + n}" for n in range(6)}


def test_an_unreachable_server_is_a_transient_error(tmp_path: Path) -> None:
    async def main() -> None:
        sink = NatsSink(
            "out", NatsSinkConfig(node="b", servers=["nats://127.0.0.1:1"], connect_timeout_s=0.2)
        )
        with pytest.raises(TransientSinkError, match="cannot reach NATS"):
            await sink.open()
        await sink.aclose()

    anyio.run(main)


def _pki(tmp: Path) -> tuple[Path, Path, Path, Path, Path]:
    """A CA, the server's certificate for 127.0.0.1 and a node's client certificate."""
    ca = trustme.CA()
    server = ca.issue_cert("127.0.0.1")
    client = ca.issue_cert("node-b.fischer")
    paths = [tmp / name for name in ("ca.pem", "srv.pem", "srv.key", "cli.pem", "cli.key")]
    ca.cert_pem.write_to_path(str(paths[0]))
    server.cert_chain_pems[0].write_to_path(str(paths[1]))
    server.private_key_pem.write_to_path(str(paths[2]))
    client.cert_chain_pems[0].write_to_path(str(paths[3]))
    client.private_key_pem.write_to_path(str(paths[4]))
    return paths[0], paths[1], paths[2], paths[3], paths[4]


def test_tls_with_a_client_certificate_from_files(tmp_path: Path) -> None:
    ca, srv, srv_key, cli, cli_key = _pki(tmp_path)
    with NatsServer(tmp_path, "b", tls=(ca, srv, srv_key)) as server:
        url = server.url.replace("nats://", "tls://")
        options = {"node": "b", "servers": [url], "connect_timeout_s": 0.5}
        tls = {"ca_file": str(ca), "cert_file": str(cli), "key_file": str(cli_key)}
        good = NatsSinkConfig.model_validate({**options, "tls": tls}, context={"environment": True})

        async def main() -> None:
            sink = NatsSink("out", good)
            await sink.open()
            await sink.send([detection("F1", 1)])
            await sink.aclose()
            assert sink.counts() == {"published": 1}
            # A certificate of another CA: the server refuses the node.
            stranger = trustme.CA().issue_cert("stranger")
            stranger.cert_chain_pems[0].write_to_path(str(tmp_path / "x.pem"))
            stranger.private_key_pem.write_to_path(str(tmp_path / "x.key"))
            other = {
                **tls,
                "cert_file": str(tmp_path / "x.pem"),
                "key_file": str(tmp_path / "x.key"),
            }
            refused = NatsSink("out", NatsSinkConfig.model_validate({**options, "tls": other}))
            with pytest.raises(TransientSinkError, match="cannot reach NATS"):
                await refused.open()
            await refused.aclose()

        anyio.run(main)
    with pytest.raises(ValidationError, match=r"missing\.pem"):
        NatsSinkConfig.model_validate(
            {**options, "tls": {**tls, "cert_file": str(tmp_path / "missing.pem")}},
            context={"environment": True},
        )


def cue_and_status() -> tuple[Handoff, OrderStatus]:
    samples = sample_events(frozenset({EventKind.HANDOFF, EventKind.ORDER_STATUS}))
    handoff = next(e for e in samples if isinstance(e, Handoff))
    status = next(e for e in samples if isinstance(e, OrderStatus))
    return handoff.model_copy(update={"battery": "GUTE.1"}), status


def test_a_handoff_or_order_status_is_refused_with_its_reason() -> None:
    handoff, status = cue_and_status()
    cue_subject = subject_for("b", handoff)
    assert cue_subject == "fsg.b.hof.GUTE_2E1"  # keyed by the battery cued
    assert subject_for("b", status) == f"fsg.b.ost.{airframe_token(status.airframe or '')}"
    taken = decode_event(cue_subject, encode_event(handoff))
    assert isinstance(taken, Handoff)
    assert (taken.event_id, taken.origin_node) == (handoff.event_id, "b")
    assert taken.operator_authorisation_required is True  # still a cue, never a command
    long_track = handoff.track.model_copy(update={"event_id": "t" * 300})
    for subject, body, reason in [
        ("fsg.b.hof.OTHER", encode_event(handoff), "battery"),
        ("fsg.b.det.GUTE_2E1", encode_event(handoff), "carries a handoff"),
        ("fsg.b.ost.GUTE_2E1", encode_event(handoff), "carries a handoff"),
        (
            cue_subject,
            encode_event(handoff.model_copy(update={"track": long_track})),
            "longer than 256",
        ),
        (
            cue_subject,
            encode_event(handoff).replace(b'"operator_authorisation_required":true', b'"x":1'),
            "not a valid event",
        ),
        (
            subject_for("b", status),
            encode_event(status.model_copy(update={"order_event_id": "o" * 300})),
            "longer than 256",
        ),
        (
            subject_for("b", status),
            encode_event(status.model_copy(update={"origin_node": "c"})),
            "relayed",
        ),
    ]:
        with pytest.raises(BadMessage, match=reason):
            decode_event(subject, body)


def test_handoffs_and_order_statuses_cross_with_their_ids_once(
    nodes: tuple[NatsServer, NatsServer],
) -> None:
    """Node b's cue and order status reach node a with the same ids, marked with their
    origin, once: a resend under the same id (after the stream's window too) is dropped."""
    hub, leaf = nodes
    handoff, status = cue_and_status()
    received: list[Event] = []

    def publish(event: Event) -> bool:
        received.append(event)
        return True

    async def main() -> tuple[NatsSink, NatsSource]:
        sink = NatsSink("out", NatsSinkConfig(node="b", servers=[leaf.url]))
        await sink.open()
        await sink.send([handoff, status])
        await sink.send([handoff])  # a retried batch: dropped by the stream
        # The same ids under new message ids (past the stream's de-duplication).
        raw = await nats.connect(leaf.url)
        for event in (handoff, status):
            await raw.jetstream().publish(
                subject_for("b", event), encode_event(event), headers={"Nats-Msg-Id": "again"}
            )
            await raw.jetstream().publish(
                subject_for("b", event), encode_event(event), headers={"Nats-Msg-Id": "x"}
            )
        await raw.close()
        source = NatsSource(
            "in",
            NatsSourceConfig(node="a", servers=[hub.url], remotes=["b"]),
            publish,
            clock=lambda: NOW,
        )
        async with anyio.create_task_group() as tg:
            await tg.start(source.run)
            with anyio.fail_after(30):
                while source.status()["counts"].get("duplicate", 0) < 2:  # type: ignore[attr-defined]  # noqa: ASYNC110
                    await anyio.sleep(0.05)
            relayed = received[0]
            await sink.send([relayed])  # node a's sink never publishes it again
            await anyio.sleep(0.3)
            tg.cancel_scope.cancel()
        await sink.aclose()
        return sink, source

    sink, source = anyio.run(main)
    assert [(e.kind, e.event_id, e.origin_node) for e in received] == [
        (EventKind.HANDOFF, handoff.event_id, "b"),
        (EventKind.ORDER_STATUS, status.event_id, "b"),
    ]
    assert source.status()["counts"] == {"handoff": 1, "order_status": 1, "duplicate": 2}
    assert sink.counts() == {"published": 2, "duplicate": 1, "relayed_skipped": 1}


def test_a_stream_made_by_an_older_version_is_updated_and_keeps_what_it_holds(
    tmp_path: Path,
) -> None:
    """``FSG_b_EVT`` made when only detections crossed: opened again it captures handoffs
    and order statuses too; with ``create_streams: false`` the difference is an error."""
    handoff, _ = cue_and_status()
    with NatsServer(tmp_path, "b") as server:

        async def main() -> tuple[list[str], int, str]:
            raw = await nats.connect(server.url)
            js = raw.jetstream()
            old = events_stream("b", {EventKind.DETECTION}, 3600.0, 1 << 20, 60.0)
            await js.add_stream(old)
            await js.publish("fsg.b.det.F1", encode_event(detection("F1", 1)))
            checked = NatsSink(
                "out", NatsSinkConfig(node="b", servers=[server.url], create_streams=False)
            )
            with pytest.raises(TransientSinkError) as refused:
                await checked.open()
            sink = NatsSink("out", NatsSinkConfig(node="b", servers=[server.url]))
            await sink.open()
            await sink.send([handoff])
            await sink.aclose()
            info = await js.stream_info("FSG_b_EVT")
            await raw.close()
            return sorted(info.config.subjects or []), info.state.messages, str(refused.value)

        subjects, messages, refusal = anyio.run(main)
    assert subjects == ["fsg.b.det.>", "fsg.b.hof.>", "fsg.b.ost.>"]
    assert messages == 2
    assert "differs: subjects" in refusal
