"""SLB reconnaissance orders: the JSON SLB offers on ``GET /orders``, and our receipts.

SLB answers ``GET {base_url}/orders?limit=N`` with ``{"orders": [ORDER, ...]}``; each ORDER
is a five-line reconnaissance order (``sinks/slb/schemas/slb-order.schema.json``, JSON
Schema draft 2020-12, whose ``$defs`` also hold the list and the receipt). ``read_order``
turns one into a ``gateway.events.FiveLineOrder`` (event id ``slb-order-<order_id>``), taking
a position as latitude and longitude, as an MGRS reference (decoded to its cell centre by
``gateway.domain.geodesy.from_mgrs``) or as a polygon. What does not fit raises
``OrderRejected`` whose message starts with the offending field's path
(``location.mgrs: ...``), which the source sends back to SLB in a "rejected" receipt.

Parsing is strict: JSON types exactly (no number in a string), times with a zone, unknown
members refused. Sizes are bounded here and by the source that reads the body.
"""

from __future__ import annotations

import json
import re
import warnings
from datetime import UTC, datetime
from importlib.resources import files
from typing import Annotated, Any, Literal

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, ValidationError

from gateway.domain.geodesy import MgrsError, from_mgrs
from gateway.errors import OrderRejected
from gateway.events import (
    FiveLineOrder,
    OrderArea,
    OrderPriority,
    OrderTask,
    Position,
)

__all__ = [
    "EVENT_ID_PREFIX",
    "MAX_REASON_CHARS",
    "ORDER_ID_PATTERN",
    "SlbOrder",
    "load_order_schema",
    "order_id_of",
    "parse_order_list",
    "read_order",
    "receipt_payload",
]

_SCHEMA_RESOURCE = "schemas/slb-order.schema.json"
_ORDER_ID_CHARS = r"[A-Za-z0-9][A-Za-z0-9._:-]{0,127}"
#: Order ids travel in a URL path (``/orders/<id>/receipt``): letters, digits and ``._:-``.
ORDER_ID_PATTERN = f"^{_ORDER_ID_CHARS}$"
_ORDER_ID = re.compile(_ORDER_ID_CHARS)
#: An order's event id is this prefix and its order id.
EVENT_ID_PREFIX = "slb-order-"
#: A rejection's reason is cut to this length.
MAX_REASON_CHARS = 512

_STRICT = ConfigDict(frozen=True, extra="forbid", strict=True)


class _Point(BaseModel):
    model_config = _STRICT

    lat_deg: float = Field(ge=-90.0, le=90.0)
    lon_deg: float = Field(ge=-180.0, le=180.0)
    alt_msl_m: float | None = Field(default=None, ge=-500.0, le=20_000.0)


class _Corner(BaseModel):
    model_config = _STRICT

    lat_deg: float = Field(ge=-90.0, le=90.0)
    lon_deg: float = Field(ge=-180.0, le=180.0)


class _Location(BaseModel):
    """Exactly one of ``point``, ``mgrs`` or ``polygon``."""

    model_config = _STRICT

    point: _Point | None = None
    mgrs: str | None = Field(default=None, min_length=1, max_length=32)
    polygon: list[_Corner] | None = Field(default=None, min_length=3, max_length=64)


class SlbOrder(BaseModel):
    """One order as SLB sends it (the schema's root)."""

    model_config = _STRICT

    order_id: str = Field(pattern=ORDER_ID_PATTERN)
    issuer: str | None = Field(default=None, max_length=128)
    issued: AwareDatetime
    airframe: str | None = Field(default=None, max_length=64)
    task: OrderTask
    location: _Location
    not_before: AwareDatetime | None = None
    not_after: AwareDatetime | None = None
    target: str | None = Field(default=None, max_length=256)
    track_id: str | None = Field(default=None, max_length=128)
    priority: OrderPriority = OrderPriority.ROUTINE
    reporting: str | None = Field(default=None, max_length=512)
    control_measures: list[Annotated[str, Field(max_length=256)]] = Field(
        default_factory=list, max_length=16
    )


def load_order_schema() -> dict[str, Any]:
    """The order JSON Schema (draft 2020-12; ``$defs``: order_list, receipt), package data."""
    text = files("sinks.slb").joinpath(_SCHEMA_RESOURCE).read_text(encoding="utf-8")
    schema: dict[str, Any] = json.loads(text)
    return schema


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


def parse_order_list(body: bytes, *, max_orders: int) -> list[object]:
    """The orders of a ``GET /orders`` body, at most ``max_orders`` (the rest wait).

    Raises ``ValueError`` when the body is not a JSON object with an ``orders`` array and
    nothing else (NaN, deep nesting and huge numbers included).
    """
    try:
        document = json.loads(body, parse_constant=_no_constant)
    except RecursionError:
        raise ValueError("nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, int digits
        raise ValueError(f"not JSON: {exc}") from None
    if not isinstance(document, dict) or not isinstance(document.get("orders"), list):
        raise ValueError('expected {"orders": [...]}')
    if set(document) != {"orders"}:
        extra = sorted(str(k) for k in document if k != "orders")
        raise ValueError(f"unexpected members {extra[:4]}")
    orders: list[object] = document["orders"][:max_orders]
    return orders


def order_id_of(element: object) -> str | None:
    """The order id of one element of the list, if it has a usable one (else None)."""
    if not isinstance(element, dict):
        return None
    value = element.get("order_id")
    if isinstance(value, str) and _ORDER_ID.fullmatch(value):
        return value
    return None


def _reason(exc: ValidationError) -> str:
    first = exc.errors(include_url=False, include_input=False)[0]
    where = ".".join(str(part) for part in first["loc"]) or "order"
    return _cut(f"{where}: {first['msg']}")


def _cut(text: str) -> str:
    return text if len(text) <= MAX_REASON_CHARS else text[: MAX_REASON_CHARS - 3] + "..."


def _area(location: _Location) -> OrderArea:
    shapes = [n for n in ("point", "mgrs", "polygon") if getattr(location, n) is not None]
    if len(shapes) != 1:
        raise OrderRejected(
            _cut(f"location: give exactly one of point, mgrs or polygon, got {shapes}")
        )
    if location.point is not None:
        p = location.point
        return OrderArea(
            point=Position(lat_deg=p.lat_deg, lon_deg=p.lon_deg, alt_msl_m=p.alt_msl_m)
        )
    if location.mgrs is not None:
        try:
            with warnings.catch_warnings():
                # GeoTrans warns, and still decodes, when the latitude band does not hold the
                # 100 km square: such a reference is inconsistent, so it is refused.
                warnings.simplefilter("error", RuntimeWarning)
                ref = from_mgrs(location.mgrs)
        except RuntimeWarning:
            raise OrderRejected(
                _cut(f"location.mgrs: {location.mgrs!r}: the grid square is not in its band")
            ) from None
        except MgrsError as exc:
            raise OrderRejected(_cut(f"location.mgrs: {exc}")) from None
        return OrderArea(
            point=Position(lat_deg=ref.lat_deg, lon_deg=ref.lon_deg), mgrs=location.mgrs
        )
    corners = location.polygon or []
    return OrderArea(polygon=tuple(Position(lat_deg=c.lat_deg, lon_deg=c.lon_deg) for c in corners))


def read_order(element: object, *, source: str) -> FiveLineOrder:
    """One element of the list as a ``FiveLineOrder`` from ``source``.

    Raises ``OrderRejected`` whose message names the offending field first.
    """
    if not isinstance(element, dict):
        raise OrderRejected("order: expected a JSON object")
    try:
        # Strict JSON mode: a time must be an RFC 3339 string with a zone, a number a number.
        order = SlbOrder.model_validate_json(json.dumps(element))
    except ValidationError as exc:
        raise OrderRejected(_reason(exc)) from None
    except RecursionError:  # json.loads took it at a shallower stack than ours
        raise OrderRejected("order: nested too deeply") from None
    if order.not_before and order.not_after and order.not_after < order.not_before:
        raise OrderRejected("not_after: before not_before")
    area = _area(order.location)
    try:
        return _five_lines(order, area, source)
    except ValidationError as exc:  # the event's own checks, should the two ever differ
        raise OrderRejected(_reason(exc)) from None


def _five_lines(order: SlbOrder, area: OrderArea, source: str) -> FiveLineOrder:
    return FiveLineOrder(
        event_id=EVENT_ID_PREFIX + order.order_id,
        order_id=order.order_id,
        source=source,
        issuer=order.issuer,
        time=order.issued,
        airframe=order.airframe,
        task=order.task,
        location=area,
        not_before=order.not_before,
        not_after=order.not_after,
        target=order.target,
        track_id=order.track_id,
        priority=order.priority,
        reporting=order.reporting,
        control_measures=tuple(order.control_measures),
    )


def receipt_payload(
    order_id: str,
    status: Literal[
        "received",
        "waiting",
        "rejected",
        "conflict",
        "accepted",
        "executing",
        "completed",
        "failed",
    ],
    *,
    time: datetime,
    reason: str | None = None,
    event_id: str | None = None,
    seq: int | None = None,
) -> dict[str, Any]:
    """The body of ``POST /orders/<order_id>/receipt`` (the schema's ``$defs/receipt``);
    ``seq``: a status's sequence number (SLB drops a receipt whose ``seq`` it has)."""
    stamp = time.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    return {
        "order_id": order_id,
        "status": status,
        "reason": None if reason is None else _cut(reason),
        "event_id": event_id,
        "time": stamp,
        "seq": seq,
    }
