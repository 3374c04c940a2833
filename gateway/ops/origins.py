"""What this node took in from other gateway nodes, for /status: per node and per airframe.

An event another node sent carries its ``origin_node`` (the ``nats`` source marks it).
``RemoteOrigins.wrap`` puts itself between a source and the bus: each such event the bus
took is counted under its node (events by kind, when last heard, how many airframes it
reported), and the airframe it concerns is listed with the node it was last heard from.
This node's own events (no ``origin_node``) pass untouched.

Bounded whatever the peers send: at most ``max_nodes`` nodes (the rest counted in
``nodes_dropped``) and the ``max_airframes`` airframes heard from most recently (older ones
forgotten, counted in ``airframes_forgotten``). This node's ``own`` airframes are never listed
as another node's: an event of one from elsewhere (a detection it made that another node
relayed, or one forged on that node's subjects) is counted under its node but does not make
the airframe that node's. A node name is at most 32 characters (the
event models check it); an airframe id is shown cut to ``AIRFRAME_CHARS``.
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime

from gateway.clock import Clock, utc_now
from gateway.events import Event

__all__ = ["AIRFRAME_CHARS", "RemoteOrigins"]

#: An airframe id longer than this is shown cut (ids from another node are its word).
AIRFRAME_CHARS = 128


@dataclass
class _Node:
    kinds: Counter[str] = field(default_factory=Counter)
    last_heard: datetime | None = None
    airframes: int = 0


class RemoteOrigins:
    """Counts of other nodes' events on this node's bus, and where each remote airframe is from."""

    def __init__(
        self,
        *,
        clock: Clock = utc_now,
        max_nodes: int = 256,
        max_airframes: int = 2000,
        own: frozenset[str] = frozenset(),
    ) -> None:
        self._clock = clock
        self._own = own
        self._max_nodes = max_nodes
        self._max_airframes = max_airframes
        self._nodes: dict[str, _Node] = {}
        #: airframe -> (node, when last heard); oldest first.
        self._airframes: OrderedDict[str, tuple[str, datetime]] = OrderedDict()
        self.nodes_dropped = 0
        self.airframes_forgotten = 0

    def wrap(self, publish: Callable[[Event], bool]) -> Callable[[Event], bool]:
        """``publish`` that also records each event from another node the bus took."""

        def publish_and_record(event: Event) -> bool:
            taken = publish(event)
            if taken and getattr(event, "origin_node", None) is not None:
                self.record(event)
            return taken

        return publish_and_record

    def record(self, event: Event) -> None:
        """Count ``event`` under its ``origin_node`` (an event without one is ignored)."""
        node_name = getattr(event, "origin_node", None)
        if not isinstance(node_name, str):
            return
        node = self._nodes.get(node_name)
        if node is None:
            if len(self._nodes) >= self._max_nodes:
                self.nodes_dropped += 1
                return
            node = self._nodes[node_name] = _Node()
        now = self._clock()
        node.kinds[event.kind.value] += 1
        node.last_heard = now
        airframe = getattr(event, "airframe", None)
        if not isinstance(airframe, str) or airframe in self._own:
            return
        airframe = airframe[:AIRFRAME_CHARS]
        before = self._airframes.pop(airframe, None)
        if before is None or before[0] != node_name:
            node.airframes += 1
            if before is not None:
                self._nodes[before[0]].airframes -= 1
        self._airframes[airframe] = (node_name, now)
        if len(self._airframes) > self._max_airframes:
            _, (old_node, _) = self._airframes.popitem(last=False)
            self._nodes[old_node].airframes -= 1
            self.airframes_forgotten += 1

    def status(self) -> dict[str, object]:
        """Per node: events taken by kind, their sum, last heard and airframes now its; per
        airframe (newest first): the node it was last heard from, and when."""
        now = self._clock()
        return {
            "nodes": {
                name: {
                    "events": sum(node.kinds.values()),
                    "by_kind": dict(node.kinds),
                    "last_heard": None if node.last_heard is None else node.last_heard.isoformat(),
                    "last_heard_age_s": (
                        None
                        if node.last_heard is None
                        else round((now - node.last_heard).total_seconds(), 3)
                    ),
                    "airframes": node.airframes,
                }
                for name, node in sorted(self._nodes.items())
            },
            "airframes": {
                airframe: {"origin_node": node, "last_heard": when.isoformat()}
                for airframe, (node, when) in reversed(self._airframes.items())
            },
            "nodes_dropped": self.nodes_dropped,
            "airframes_forgotten": self.airframes_forgotten,
        }
