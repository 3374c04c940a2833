"""A SWECCIS ``Orders`` document read into a ``FiveLineOrder``, every field checked.

The document is untrusted: each element and attribute is checked against what the schema
(``schemas/sweccis-fas.xsd``) allows, unknown elements and attributes are refused, and
every failure is a ``DocumentError`` naming the element (``Orders/FiveLineOrder/Location/Mgrs``)
and carrying the document's id, so the server is told which order was rejected and why. An
MGRS location is decoded with ``gateway.domain.geodesy.from_mgrs`` to its cell centre and the
reference is kept as written.

The event: ``event_id`` ``sweccis-order-<OrderId>`` (the same order received again is the
same event, whichever connection or server brought it), ``source`` the source's name.
"""

from __future__ import annotations

import re
from typing import TypeVar

from pydantic import ValidationError

from gateway.domain.geodesy import MgrsError, from_mgrs
from gateway.events import (
    ALT_MAX_M,
    ALT_MIN_M,
    FiveLineOrder,
    OrderArea,
    OrderPriority,
    OrderTask,
    Position,
)
from sinks.sweccis.fasxml import Node

__all__ = ["EVENT_ID_PREFIX", "decode_order"]

#: Every order's ``event_id`` is this followed by the issuer's order id.
EVENT_ID_PREFIX = "sweccis-order-"
_MGRS = re.compile(
    r"[0-9]{1,2} ?[C-HJ-NP-X] ?[A-HJ-NP-Z]{2} ?"
    r"([0-9]{3} ?[0-9]{3}|[0-9]{4} ?[0-9]{4}|[0-9]{5} ?[0-9]{5})"
)
_FIELDS = {
    "OrderId": 1,
    "Issuer": 1,
    "Time": 1,
    "Airframe": 1,
    "Task": 1,
    "Location": 1,
    "Window": 1,
    "Target": 1,
    "Priority": 1,
    "Reporting": 1,
    "ControlMeasures": 1,
}
_Choice = TypeVar("_Choice", OrderTask, OrderPriority)
_POINT = frozenset({"latDeg", "lonDeg", "altMslM", "altHaeM"})
_ALT = (ALT_MIN_M, ALT_MAX_M)


def _one(node: Node, kids: dict[str, list[Node]], name: str) -> Node:
    found = kids.get(name)
    if not found:
        raise node.fail(f"<{name}> is required")
    return found[0]


def _optional_text(kids: dict[str, list[Node]], name: str, max_length: int) -> str | None:
    found = kids.get(name)
    return found[0].text(max_length=max_length, min_length=1) if found else None


def _choice(node: Node, kind: type[_Choice]) -> _Choice:
    text = node.text(max_length=32)
    try:
        return kind(text)
    except ValueError:
        allowed = ", ".join(member.value for member in kind)
        raise node.fail(f"{text!r} is not one of {allowed}") from None


def _corner(node: Node, attributes: frozenset[str]) -> Position:
    node.check_attributes(attributes)
    if len(node.element):
        raise node.fail("expected no child elements")
    return Position(
        lat_deg=node.required_double("latDeg", -90.0, 90.0),
        lon_deg=node.required_double("lonDeg", -180.0, 180.0),
        alt_msl_m=node.double("altMslM", *_ALT),
        alt_hae_m=node.double("altHaeM", *_ALT),
    )


def _location(node: Node) -> OrderArea:
    node.check_attributes(frozenset())
    kids = node.children({"Point": 1, "Polygon": 1, "Mgrs": 1})
    if len(kids) != 1:
        raise node.fail("expected exactly one of <Point>, <Polygon> or <Mgrs>")
    if "Point" in kids:
        return OrderArea(point=_corner(kids["Point"][0], _POINT))
    if "Polygon" in kids:
        polygon = kids["Polygon"][0]
        polygon.check_attributes(frozenset())
        corners = polygon.children({"Corner": 64}).get("Corner", [])
        if len(corners) < 3:
            raise polygon.fail(f"an area needs 3 to 64 <Corner>s, found {len(corners)}")
        latlon = frozenset({"latDeg", "lonDeg"})
        return OrderArea(polygon=tuple(_corner(corner, latlon) for corner in corners))
    mgrs = kids["Mgrs"][0]
    mgrs.check_attributes(frozenset())
    text = mgrs.text(max_length=32, min_length=1)
    if not _MGRS.fullmatch(text):
        raise mgrs.fail(f"{text!r} is not an MGRS reference of 3, 4 or 5 digits each")
    try:
        ref = from_mgrs(text)
    except MgrsError as exc:
        raise mgrs.fail(str(exc)) from None
    return OrderArea(point=Position(lat_deg=ref.lat_deg, lon_deg=ref.lon_deg), mgrs=text)


def _control_measures(node: Node) -> tuple[str, ...]:
    node.check_attributes(frozenset())
    measures = node.children({"Measure": 16}).get("Measure", [])
    if not measures:
        raise node.fail("expected 1 to 16 <Measure>s")
    return tuple(measure.text(max_length=256, min_length=1) for measure in measures)


def decode_order(node: Node, *, source: str) -> FiveLineOrder:
    """The ``FiveLineOrder`` of an ``Orders`` root element (``node``, its id already read).

    Raises ``DocumentError`` naming the element and carrying ``node.doc_id``.
    """
    body = _one(node, node.children({"FiveLineOrder": 1}), "FiveLineOrder")
    body.check_attributes(frozenset())
    kids = body.children(_FIELDS)
    order_id = _one(body, kids, "OrderId").text(max_length=128, min_length=1)
    time = _one(body, kids, "Time").text_time()
    not_before = not_after = None
    if "Window" in kids:
        window = kids["Window"][0]
        window.check_attributes(frozenset({"notBefore", "notAfter"}))
        not_before, not_after = window.time("notBefore"), window.time("notAfter")
        if not_before is not None and not_after is not None and not_after < not_before:
            raise window.fail("notAfter is before notBefore")
    target = track_id = None
    if "Target" in kids:
        target_node = kids["Target"][0]
        target_node.check_attributes(frozenset({"trackId"}))
        target = target_node.text(max_length=256) or None
        track_id = target_node.attribute("trackId")
        if track_id is not None and not 1 <= len(track_id) <= 128:
            raise target_node.fail("expected 1 to 128 characters", "trackId")
    priority = (
        _choice(kids["Priority"][0], OrderPriority) if "Priority" in kids else OrderPriority.ROUTINE
    )
    fields = {
        "event_id": EVENT_ID_PREFIX + order_id,
        "order_id": order_id,
        "source": source,
        "issuer": _optional_text(kids, "Issuer", 128),
        "time": time,
        "airframe": _optional_text(kids, "Airframe", 64),
        "task": _choice(_one(body, kids, "Task"), OrderTask),
        "location": _location(_one(body, kids, "Location")),
        "not_before": not_before,
        "not_after": not_after,
        "target": target,
        "track_id": track_id,
        "priority": priority,
        "reporting": _optional_text(kids, "Reporting", 512),
        "control_measures": _control_measures(kids["ControlMeasures"][0])
        if "ControlMeasures" in kids
        else (),
    }
    for name, simple in kids.items():
        # Elements with text only: a child element inside one is refused by text() above,
        # attributes on them here (Window, Target, Location and lists check their own).
        if name not in ("Window", "Target", "Location", "ControlMeasures"):
            simple[0].check_attributes(frozenset())
    try:
        return FiveLineOrder.model_validate(fields)
    except ValidationError as exc:
        # Every field was checked above; this is the model's last word, named as well.
        problem = exc.errors()[0]
        where = ".".join(str(part) for part in problem["loc"]) or "order"
        raise body.fail(f"{where}: {problem['msg']}") from None
