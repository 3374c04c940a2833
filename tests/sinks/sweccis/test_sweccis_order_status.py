"""The SWECCIS OrderStatus document: what the source tells the server of an order's states."""

from __future__ import annotations

from datetime import UTC, datetime

from hypothesis import given
from hypothesis import strategies as st
from lxml import etree

from gateway.events import OrderState, OrderStatus
from sinks.sweccis.fas import encode_order_status, load_schema
from sinks.sweccis.fasxml import NAMESPACE

SCHEMA = etree.XMLSchema(etree.fromstring(load_schema()))
NS = f"{{{NAMESPACE}}}"


def status(**changes: object) -> OrderStatus:
    fields: dict[str, object] = {
        "event_id": "sweccis-order-ORD-1-rejected",
        "order_event_id": "sweccis-order-ORD-1",
        "order_id": "ORD-1",
        "source": "brigade-orders",
        "airframe": "F26E-001",
        "time": datetime(2026, 11, 22, 12, 0, tzinfo=UTC),
        "status": OrderState.REJECTED,
        "check": "terrain",
        "reason": "commanded 500.0 m MSL is below the floor 665.1 m MSL",
    }
    return OrderStatus.model_validate({**fields, **changes})


def test_a_rejection_carries_check_and_reason_and_is_valid() -> None:
    document = etree.fromstring(encode_order_status(status()))
    assert SCHEMA.validate(document), SCHEMA.error_log
    assert document.get("id") == "sweccis-order-ORD-1-rejected"
    assert document.findtext(f"{NS}Status") == "rejected"
    assert document.findtext(f"{NS}Check") == "terrain"
    assert document.findtext(f"{NS}Time") == "2026-11-22T12:00:00.000Z"


@given(
    st.sampled_from(list(OrderState)),
    st.text(max_size=600) | st.none(),
    st.integers(min_value=0, max_value=500) | st.none(),
)
def test_any_status_is_schema_valid(
    state: OrderState, reason: str | None, items: int | None
) -> None:
    """Reasons are our own free text: anything XML cannot carry is replaced, never refused."""
    made = status(
        status=state, reason=None if reason is None else reason[:512], mission_items=items
    )
    assert SCHEMA.validate(etree.fromstring(encode_order_status(made))), SCHEMA.error_log
