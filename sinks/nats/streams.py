"""The JetStream streams of a node, made from config or checked when ops made them.

Per node N (its server runs JetStream with ``domain: N``):

- ``FSG_N_EVT`` captures ``fsg.N.det.>``, ``fsg.N.hof.>`` and ``fsg.N.ost.>``: detections,
  handoffs and order statuses, file storage, kept ``max_age``, discard old, de-duplicated by
  ``Nats-Msg-Id`` within ``duplicate_window``;
- ``FSG_N_TLM`` captures ``fsg.N.tlm.>`` with one message per subject: the newest state
  of each airframe, all that crosses a thin link;
- ``FSG_N_PIC`` (on an aggregating node) sources every remote node's EVT and TLM through
  its JetStream domain (``$JS.<remote>.API``) over the leaf link; it de-duplicates by
  Msg-Id too, so a detection two nodes heard is stored once.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence

from nats.js import JetStreamContext
from nats.js.api import (
    DiscardPolicy,
    ExternalStream,
    RetentionPolicy,
    StorageType,
    StreamConfig,
    StreamSource,
)
from nats.js.errors import NotFoundError

from gateway.errors import GatewayError
from gateway.events import EventKind
from sinks.nats.subjects import KIND_TOKENS

__all__ = [
    "StreamMismatch",
    "aggregate_stream",
    "ensure_stream",
    "events_stream",
    "telemetry_stream",
]


class StreamMismatch(GatewayError):
    """A stream ops created differs from what the config needs; the text says how."""


def events_stream(
    node: str,
    kinds: Collection[EventKind],
    max_age_s: float,
    max_bytes: int,
    dup_window_s: float,
) -> StreamConfig:
    """``FSG_<node>_EVT``: this node's detections, handoffs and order statuses (of ``kinds``)."""
    return StreamConfig(
        name=f"FSG_{node}_EVT",
        subjects=[
            f"fsg.{node}.{token}.>"
            for kind, token in KIND_TOKENS.items()
            if kind in kinds and kind is not EventKind.TELEMETRY
        ],
        retention=RetentionPolicy.LIMITS,
        storage=StorageType.FILE,
        discard=DiscardPolicy.OLD,
        max_age=max_age_s,
        max_bytes=max_bytes,
        duplicate_window=dup_window_s,
    )


def telemetry_stream(node: str, max_age_s: float) -> StreamConfig:
    """``FSG_<node>_TLM``: the newest state of each of this node's airframes."""
    return StreamConfig(
        name=f"FSG_{node}_TLM",
        subjects=[f"fsg.{node}.tlm.>"],
        retention=RetentionPolicy.LIMITS,
        storage=StorageType.FILE,
        discard=DiscardPolicy.OLD,
        max_age=max_age_s,
        max_msgs_per_subject=1,
        duplicate_window=min(max_age_s, 120.0),
    )


def aggregate_stream(
    node: str, remotes: Sequence[str], max_age_s: float, max_bytes: int, dup_window_s: float
) -> StreamConfig:
    """``FSG_<node>_PIC``: every remote node's detections and newest airframe states."""
    sources = [
        StreamSource(
            name=f"FSG_{remote}_{part}",
            external=ExternalStream(api=f"$JS.{remote}.API"),
        )
        for remote in remotes
        for part in ("EVT", "TLM")
    ]
    return StreamConfig(
        name=f"FSG_{node}_PIC",
        sources=sources,
        retention=RetentionPolicy.LIMITS,
        storage=StorageType.FILE,
        discard=DiscardPolicy.OLD,
        max_age=max_age_s,
        max_bytes=max_bytes,
        duplicate_window=dup_window_s,
    )


def _differences(wanted: StreamConfig, actual: StreamConfig) -> list[str]:
    found: list[str] = []
    if sorted(wanted.subjects or []) != sorted(actual.subjects or []):
        found.append(f"subjects {actual.subjects} (wanted {wanted.subjects})")
    want_sources = sorted(s.name for s in wanted.sources or [])
    have_sources = sorted(s.name for s in actual.sources or [])
    if want_sources != have_sources:
        found.append(f"sources {have_sources} (wanted {want_sources})")
    if wanted.max_msgs_per_subject not in (None, -1) and (
        actual.max_msgs_per_subject != wanted.max_msgs_per_subject
    ):
        found.append(f"max_msgs_per_subject {actual.max_msgs_per_subject}")
    return found


async def ensure_stream(js: JetStreamContext, wanted: StreamConfig, *, create: bool) -> None:
    """Create ``wanted`` if missing (when ``create``), else check the one there.

    With ``create``, a stream the gateway made from an older config (capturing fewer kinds,
    sourcing fewer remotes) is updated to ``wanted``: subjects and sources only grow or
    change, what it holds is kept. ``StreamMismatch`` when ops made it (``create`` off) and it
    captures other subjects or sources other streams, or when it is missing.
    """
    name = wanted.name or ""
    try:
        info = await js.stream_info(name)
    except NotFoundError:
        if not create:
            raise StreamMismatch(
                f"stream {name} does not exist and create_streams is off"
            ) from None
        await js.add_stream(wanted)
        return
    problems = _differences(wanted, info.config)
    if problems and create:
        await js.update_stream(wanted)
    elif problems:
        raise StreamMismatch(f"stream {name} differs: " + "; ".join(problems))
