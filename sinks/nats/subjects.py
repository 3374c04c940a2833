"""Subjects, message ids and message bodies of the events nodes exchange over NATS.

A subject is ``fsg.<node>.<kind>.<airframe token>``: the node token is the origin, so a
stream on one node never captures another node's subjects. An airframe id may hold ``.``,
``*``, ``>`` or spaces, which NATS reads as structure; the token keeps ASCII letters, digits
and ``-`` and writes every other byte of the UTF-8 id as ``_XX`` (hex), so it is reversible
and a filter on one airframe still works. An id whose token would pass ``MAX_TOKEN`` is
cut and ends in a hash of the whole id.
"""

from __future__ import annotations

import hashlib
import math
import re
from datetime import datetime, timedelta

from pydantic import BaseModel, ValidationError

from gateway.clock import utc_now
from gateway.errors import GatewayError
from gateway.events import (
    Detection,
    Event,
    EventKind,
    Handoff,
    OrderStatus,
    Telemetry,
    event_adapter,
)

__all__ = [
    "KIND_TOKENS",
    "MAX_AHEAD_S",
    "MAX_BODY_BYTES",
    "MAX_ID_CHARS",
    "MAX_ITEMS",
    "MAX_SIGMA_M",
    "MAX_TEXT_CHARS",
    "MAX_TOKEN",
    "NODE_PATTERN",
    "BadMessage",
    "Carried",
    "airframe_token",
    "decode_event",
    "encode_event",
    "key_of",
    "node_of",
    "subject_for",
]

#: A node's name: a NATS subject token, a stream-name part and a JetStream domain at once.
NODE_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"
#: The kinds that cross between nodes, and their subject tokens.
KIND_TOKENS: dict[EventKind, str] = {
    EventKind.DETECTION: "det",
    EventKind.TELEMETRY: "tlm",
    EventKind.HANDOFF: "hof",
    EventKind.ORDER_STATUS: "ost",
}
#: What a node takes from another: every carried kind.
Carried = Detection | Telemetry | Handoff | OrderStatus
_TOKEN_KINDS = {token: kind for kind, token in KIND_TOKENS.items()}
MAX_TOKEN = 96
#: A body larger than this is refused on the way in (an event is well under 4 KiB).
MAX_BODY_BYTES = 64 * 1024
#: An event id or airframe id longer than this is refused on the way in: a node's own are
#: under 128 characters, and the source remembers the ids it took (``remember_ids`` of them).
MAX_ID_CHARS = 256
#: Any other text of a remote event (a class, a subtype, a link label, ...) is refused longer
#: than this: it reaches CoT remarks, the map and every C2 sink.
MAX_TEXT_CHARS = 256
#: A list of a remote event is refused longer than this.
MAX_ITEMS = 64
#: A remote detection's ``sigma_h_m`` is refused above this, as the ingest refuses one.
MAX_SIGMA_M = 10_000.0
#: A remote event dated more than this ahead of this node's clock is refused: it would keep
#: its track from ever ageing out (the ingest does not believe an airframe a minute ahead;
#: nodes' clocks may differ a little more).
MAX_AHEAD_S = 300.0
#: Integers beyond this are refused (no field of an event needs more than 64 bits).
_MAX_INT = 2**63
_PLAIN = re.compile(rb"[A-Za-z0-9-]")
_ALL_PLAIN = re.compile(r"[A-Za-z0-9-]+", re.ASCII)
_NODE = re.compile(NODE_PATTERN)


class BadMessage(GatewayError):
    """A message from NATS that is not an event this node takes; the text says why."""


def airframe_token(airframe: str) -> str:
    """``airframe`` as one subject token (reversible unless cut to ``MAX_TOKEN``)."""
    if len(airframe) <= MAX_TOKEN and _ALL_PLAIN.fullmatch(airframe):
        return airframe  # the usual id: nothing to escape (twice per event each way)
    token = "".join(
        chr(byte) if _PLAIN.fullmatch(bytes((byte,))) else f"_{byte:02X}"
        for byte in airframe.encode()
    )
    if not token:
        return "_"
    if len(token) <= MAX_TOKEN:
        return token
    digest = hashlib.sha256(airframe.encode()).hexdigest()[:16]
    return f"{token[: MAX_TOKEN - 18]}_H{digest}"


def key_of(event: Event) -> str:
    """What the last subject token names: the airframe; a handoff's battery; an order
    status's airframe (empty when the order went to none)."""
    if isinstance(event, Handoff):
        return event.battery
    return str(getattr(event, "airframe", None) or "")


def subject_for(node: str, event: Event) -> str:
    """The subject of ``event`` published by ``node``; ``KeyError`` for a kind not carried."""
    token = KIND_TOKENS[event.kind]
    return f"fsg.{node}.{token}.{airframe_token(key_of(event))}"


def encode_event(event: Event) -> bytes:
    """The message body: the event's JSON (its ``origin_node`` is never set here)."""
    return event.model_dump_json(exclude_none=True).encode()


def node_of(subject: str) -> tuple[str, EventKind]:
    """The origin node and kind a subject names; ``BadMessage`` if it is not one of ours."""
    parts = subject.split(".")
    if len(parts) != 4 or parts[0] != "fsg":
        raise BadMessage(f"subject {subject[:120]!r} is not fsg.<node>.<kind>.<airframe>")
    node, token = parts[1], parts[2]
    if not _NODE.fullmatch(node):
        raise BadMessage(f"subject {subject[:120]!r}: node {node[:40]!r} is not a node name")
    kind = _TOKEN_KINDS.get(token)
    if kind is None:
        raise BadMessage(f"subject {subject[:120]!r}: kind {token[:20]!r} is not carried")
    return node, kind


def _ids(event: Carried) -> list[str]:
    """The ids of ``event`` the source keeps or compares: each at most ``MAX_ID_CHARS``."""
    ids = [event.event_id, key_of(event)]
    if isinstance(event, Handoff):
        ids += [event.handoff_id, event.track.event_id, event.superseded_by or ""]
    elif isinstance(event, OrderStatus):
        ids.append(event.order_event_id)
    return ids


def decode_event(subject: str, body: bytes) -> Carried:
    """The event a message carries, marked with its node of origin.

    ``BadMessage`` for an oversize body, invalid JSON or event, a kind the subject does not
    name, an id longer than ``MAX_ID_CHARS`` (event, airframe, handoff, track, order), a value
    out of bounds (``unbounded``; a detection's ``sigma_h_m`` above ``MAX_SIGMA_M``), an
    airframe (a handoff's battery) the subject does not name, or a body that already names an
    origin (a node never sends on another node's events).
    """
    node, kind = node_of(subject)
    if len(body) > MAX_BODY_BYTES:
        raise BadMessage(f"subject {subject[:120]!r}: body of {len(body)} bytes is too large")
    try:
        event = event_adapter.validate_json(body)
    except ValidationError as exc:
        raise BadMessage(f"subject {subject[:120]!r}: not a valid event ({_first(exc)})") from None
    except ValueError as exc:
        raise BadMessage(f"subject {subject[:120]!r}: not a valid event ({exc})") from None
    if event.kind is not kind or not isinstance(event, Carried):
        raise BadMessage(f"subject {subject[:120]!r}: carries a {event.kind.value} event")
    if any(len(value) > MAX_ID_CHARS for value in _ids(event)):
        raise BadMessage(f"subject {subject[:120]!r}: an id is longer than {MAX_ID_CHARS}")
    problem = unbounded(event, utc_now() + timedelta(seconds=MAX_AHEAD_S))
    if problem is not None:
        raise BadMessage(f"subject {subject[:120]!r}: {problem}")
    if isinstance(event, Detection) and event.sigma_h_m > MAX_SIGMA_M:
        raise BadMessage(f"subject {subject[:120]!r}: sigma_h_m above {MAX_SIGMA_M:.0f} m")
    if airframe_token(key_of(event)) != subject.split(".")[3]:
        what = "battery" if isinstance(event, Handoff) else "airframe"
        raise BadMessage(f"subject {subject[:120]!r}: event of {what} {key_of(event)[:64]!r}")
    if event.origin_node is not None:
        raise BadMessage(f"subject {subject[:120]!r}: event relayed from {event.origin_node!r}")
    return event.model_copy(update={"origin_node": node})


def unbounded(value: object, latest: datetime, where: str = "event") -> str | None:
    """What of ``value`` (an event, walked through) is out of bounds, in words; None if nothing.

    Text longer than ``MAX_TEXT_CHARS``, a list longer than ``MAX_ITEMS``, a number that is
    not finite (JSON's ``NaN``, ``Infinity``, or ``1e400``) or an integer beyond 64 bits, a
    time after ``latest``. The model checked every field's type and its own ranges.
    """
    if isinstance(value, str):
        if len(value) > MAX_TEXT_CHARS:
            return f"{where} is longer than {MAX_TEXT_CHARS} characters"
    elif isinstance(value, float):
        if not math.isfinite(value):
            return f"{where} is not a finite number"
    elif isinstance(value, bool) or value is None:
        pass
    elif isinstance(value, int):
        if not -_MAX_INT <= value < _MAX_INT:
            return f"{where} is out of range"
    elif isinstance(value, datetime):
        if value > latest:
            return f"{where} is more than {MAX_AHEAD_S:.0f} s ahead of this node's clock"
    elif isinstance(value, BaseModel):
        for name, item in value.__dict__.items():
            problem = unbounded(item, latest, name)
            if problem is not None:
                return problem
    elif isinstance(value, tuple | list):
        if len(value) > MAX_ITEMS:
            return f"{where} holds more than {MAX_ITEMS} items"
        for item in value:
            problem = unbounded(item, latest, where)
            if problem is not None:
                return problem
    elif isinstance(value, dict):
        if len(value) > MAX_ITEMS:
            return f"{where} holds more than {MAX_ITEMS} items"
        for key, item in value.items():
            problem = unbounded(key, latest, where) or unbounded(item, latest, f"{where}.{key}")
            if problem is not None:
                return problem
    return None


def _first(exc: ValidationError) -> str:
    """The first problem of ``exc`` in one short line: where it is and what is wrong (no input)."""
    errors = exc.errors(include_url=False, include_input=False)
    if not errors:
        return "invalid"
    # The union's tag is the first part of a location: the field path follows it.
    where = ".".join(str(part) for part in errors[0]["loc"][1:])[:120]
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{where or 'body'}: {errors[0]['msg'][:120]}{more}"
