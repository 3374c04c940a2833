"""The sources' order-status feed (``gateway.c2.source.OrderStatusFeed``)."""

from __future__ import annotations

from datetime import UTC, datetime

from gateway.c2.source import OrderStatusFeed
from gateway.events import OrderState, OrderStatus


class Listener:
    name = "slb"

    def __init__(self) -> None:
        self.statuses: list[OrderStatus] = []

    def on_order_status(self, status: OrderStatus) -> None:
        self.statuses.append(status)


def status(event_id: str, origin_node: str | None) -> OrderStatus:
    return OrderStatus(
        event_id=event_id,
        order_event_id="o-1",
        order_id="ORD-1",
        source="slb",
        time=datetime(2026, 11, 27, 8, 0, tzinfo=UTC),
        status=OrderState.ACCEPTED,
        origin_node=origin_node,
    )


def test_another_nodes_status_answers_no_issuer_of_this_node() -> None:
    """A status another node sent (its ``origin_node`` set) is not this node's to report,
    even when it names a source of the same name."""
    feed = OrderStatusFeed()
    listener = Listener()
    feed.add(listener)
    feed.offer_slot(status("o-1-accepted", None), 0.0, None)
    feed.offer_slot(status("o-1-accepted-remote", "b"), 0.0, None)
    assert [s.event_id for s in listener.statuses] == ["o-1-accepted"]
