"""The current picture the map shows: bounded layers of entities, and the changes to them.

``Picture.apply(event)`` folds one event into the picture and returns the changes it made,
each a JSON-ready dict (docs/map.md §4): ``{"op": "upsert", "layer", "id", "data"}`` with the
entity's whole current state, or ``{"op": "remove", "layer", "id", "reason"}``. The layers:

- ``airframe``: our airframes, from ``Telemetry`` (position, battery, endurance, active link)
  and ``LinkState`` (each link's health), and other nodes' airframes (``origin_node``: the
  node their state came from);
- ``track``: fused tracks while they live, with a short bounded history of positions; a
  ``lost`` or ``merged`` track is removed;
- ``blue``: friendly units (``BlueForce``);
- ``cue``: GUTE II handoffs with their last revisions and status;
- ``order``: five-line orders and the orders processor's status of each;
- ``detection``: the newest detections.

Every layer is capped (``MapSinkConfig``): a new entity beyond the cap evicts the one updated
longest ago, as a ``remove`` with reason ``evicted``. Entities not updated for
``expire_after_s`` are removed as ``expired``. Text from outside (callsigns, classes) is kept
as text: the page never reads it as HTML. Nothing here does I/O.
"""

from __future__ import annotations

import math
import re
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from gateway.events import (
    BlueForce,
    Detection,
    Event,
    FiveLineOrder,
    Handoff,
    LinkState,
    OrderStatus,
    Position,
    Telemetry,
    Track,
)

__all__ = ["LAYERS", "Change", "Limits", "Picture"]

#: The layers, in the order the page draws them (lowest first).
LAYERS = ("order", "detection", "cue", "blue", "track", "airframe")

Change = dict[str, Any]

#: A symbol identification code milsymbol can draw: 15 letters (2525B/C, APP-6A/B) or 20/30
#: digits (2525D/E, APP-6D). Anything else from a peer is replaced by a generic code.
_SIDC = re.compile(r"^(?:[A-Za-z0-9*-]{15}|[0-9]{20}|[0-9]{30})$")
_GENERIC_TRACK = {
    "hostile": "SHGP-----------",
    "suspect": "SSGP-----------",
    "neutral": "SNGP-----------",
    "friend": "SFGP-----------",
    "unknown": "SUGP-----------",
}
_AIRFRAME_SIDC = "SFAPMFQ--------"  # friendly air, military fixed wing, UAV
_BLUE_SIDC = "SFGPU----------"  # friendly ground unit
_BATTERY_SIDC = "SFGPUCDM-------"  # friendly air defence, missile
#: An airframe heard of only through its links so far: every telemetry field unknown.
_NO_TELEMETRY: dict[str, Any] = {
    "time": None,
    "sidc": _AIRFRAME_SIDC,
    "heading_deg": None,
    "groundspeed_mps": None,
    "battery_pct": None,
    "endurance_min": None,
    "active_link": None,
    "armed": None,
    "links": {},
    "origin_node": None,
}


@dataclass(frozen=True, slots=True)
class Limits:
    """How many entities each layer keeps, and how long an unchanged one stays."""

    airframes: int = 500
    tracks: int = 2000
    blue: int = 2000
    cues: int = 500
    orders: int = 500
    detections: int = 500
    history_points: int = 20
    cue_revisions: int = 10
    expire_after_s: float = 900.0

    def cap(self, layer: str) -> int:
        """The cap of ``layer``."""
        return {
            "airframe": self.airframes,
            "track": self.tracks,
            "blue": self.blue,
            "cue": self.cues,
            "order": self.orders,
            "detection": self.detections,
        }[layer]


def _round(value: float | None, digits: int = 1) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return round(value, digits)


def _where(position: Position | None) -> dict[str, float | None]:
    if position is None:
        return {"lat": None, "lon": None, "alt_msl_m": None}
    return {
        "lat": round(position.lat_deg, 7),
        "lon": round(position.lon_deg, 7),
        "alt_msl_m": _round(position.alt_msl_m),
    }


def _sidc(code: str | None, fallback: str) -> str:
    return code if code is not None and _SIDC.match(code) else fallback


class Picture:
    """The map's current picture; ``apply`` returns what changed, ``snapshot`` all of it."""

    def __init__(self, limits: Limits, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.limits = limits
        self._clock = clock
        self._layers: dict[str, OrderedDict[str, dict[str, Any]]] = {
            layer: OrderedDict() for layer in LAYERS
        }
        self._seen: dict[str, dict[str, float]] = {layer: {} for layer in LAYERS}
        self._history: dict[str, deque[tuple[float, float]]] = {}
        self._revisions: dict[str, deque[dict[str, Any]]] = {}
        self.evicted = 0
        self.expired = 0

    # -- reading ---------------------------------------------------------------------------

    def snapshot(self) -> dict[str, list[dict[str, Any]]]:
        """Every entity of every layer, oldest update first."""
        return {layer: list(entities.values()) for layer, entities in self._layers.items()}

    def sizes(self) -> dict[str, int]:
        """How many entities each layer holds."""
        return {layer: len(entities) for layer, entities in self._layers.items()}

    def get(self, layer: str, key: str) -> dict[str, Any] | None:
        """One entity, or None."""
        return self._layers[layer].get(key)

    # -- changing --------------------------------------------------------------------------

    def apply(self, event: Event) -> list[Change]:
        """Fold ``event`` into the picture; the changes it made (none for other kinds)."""
        handler = _HANDLERS.get(type(event))
        return [] if handler is None else handler(self, event)

    def expire(self) -> list[Change]:
        """Remove every entity not updated for ``expire_after_s``; the removals."""
        horizon = self._clock() - self.limits.expire_after_s
        changes: list[Change] = []
        for layer in LAYERS:
            seen = self._seen[layer]
            for key in [k for k, at in seen.items() if at < horizon]:
                changes.append(self._remove(layer, key, "expired"))
                self.expired += 1
        return changes

    def _upsert(self, layer: str, key: str, data: dict[str, Any]) -> list[Change]:
        entities = self._layers[layer]
        changes: list[Change] = []
        if key in entities:
            entities.move_to_end(key)
        else:
            while len(entities) >= self.limits.cap(layer):
                oldest = next(iter(entities))
                changes.append(self._remove(layer, oldest, "evicted"))
                self.evicted += 1
        entities[key] = data
        self._seen[layer][key] = self._clock()
        changes.append({"op": "upsert", "layer": layer, "id": key, "data": data})
        return changes

    def _remove(self, layer: str, key: str, reason: str) -> Change:
        self._layers[layer].pop(key, None)
        self._seen[layer].pop(key, None)
        if layer == "track":
            self._history.pop(key, None)
        elif layer == "cue":
            self._revisions.pop(key, None)
        return {"op": "remove", "layer": layer, "id": key, "reason": reason}

    def _telemetry(self, event: Telemetry) -> list[Change]:
        old = self._layers["airframe"].get(event.airframe)
        data: dict[str, Any] = {
            "id": event.airframe,
            "time": event.time.isoformat(),
            **_where(event.position),
            "sidc": _AIRFRAME_SIDC,
            "heading_deg": _round(event.heading_deg),
            "groundspeed_mps": _round(event.groundspeed_mps),
            "battery_pct": _round(event.battery_pct),
            "endurance_min": _round(event.endurance_remaining_min),
            "active_link": event.active_link,
            "armed": event.is_armed,
            "links": {} if old is None else old["links"],
            "origin_node": event.origin_node,
        }
        return self._upsert("airframe", event.airframe, data)

    def _link_state(self, event: LinkState) -> list[Change]:
        old = self._layers["airframe"].get(event.airframe)
        data: dict[str, Any] = {"id": event.airframe, **_where(None), **_NO_TELEMETRY}
        if old is not None:
            data.update(old)
        links = dict(data.get("links", {}))
        # An airframe has a handful of links; a peer cannot add more (the config names them).
        links[event.link] = {
            "up": event.is_up,
            "active": event.is_active,
            "loss_pct": _round(event.loss_pct),
            "reason": event.reason,
            "time": event.time.isoformat(),
        }
        data["links"] = links
        if event.is_active:
            data["active_link"] = event.link
        return self._upsert("airframe", event.airframe, data)

    def _track(self, event: Track) -> list[Change]:
        if event.status in ("lost", "merged"):
            if event.track_id not in self._layers["track"]:
                return []
            return [self._remove("track", event.track_id, event.status)]
        history = self._history.get(event.track_id)
        if history is None:
            history = deque(maxlen=self.limits.history_points)
        point = (round(event.position.lat_deg, 7), round(event.position.lon_deg, 7))
        if not history or history[-1] != point:
            history.append(point)
        data = {
            "id": event.track_id,
            "time": event.time.isoformat(),
            **_where(event.position),
            "status": event.status,
            "object_class": event.object_class,
            "subtype": event.subtype,
            "confidence": round(event.confidence, 3),
            "hostility": event.hostility,
            "sidc": _sidc(event.sidc, _GENERIC_TRACK[event.hostility]),
            "cep50_m": _round(event.cep50_m),
            "cep90_m": _round(event.cep90_m),
            "course_deg": _round(event.course_deg),
            "speed_mps": _round(event.speed_mps),
            "airframes": list(event.airframes),
            "origin_nodes": list(event.origin_nodes),
            "sensors": [s.value for s in event.sensors],
            "detection_count": event.detection_count,
            "history": [list(p) for p in history],
        }
        changes = self._upsert("track", event.track_id, data)
        self._history[event.track_id] = history  # after _upsert, which may evict others
        return changes

    def _blue(self, event: BlueForce) -> list[Change]:
        data = {
            "id": event.uid,
            "time": event.time.isoformat(),
            **_where(event.position),
            "callsign": event.callsign,
            "sidc": _sidc(event.sidc, _BLUE_SIDC),
            "course_deg": _round(event.course_deg),
            "speed_mps": _round(event.speed_mps),
            "source": event.source_name or event.source,
            "provenance": event.provenance.value,
        }
        return self._upsert("blue", event.uid, data)

    def _handoff(self, event: Handoff) -> list[Change]:
        revisions = self._revisions.get(event.handoff_id)
        if revisions is None:
            revisions = deque(maxlen=self.limits.cue_revisions)
        old = self._layers["cue"].get(event.handoff_id)
        if old is not None and event.revision < old["revision"]:
            return []  # an older revision delivered late: the newer one stands
        decon = event.deconfliction
        summary = {
            "revision": event.revision,
            "time": event.time.isoformat(),
            "status": event.status,
            "recommended_effector": event.recommended_effector,
            "clear": decon.clear,
            "note": event.note,
        }
        if not revisions or revisions[-1]["revision"] != event.revision:
            revisions.append(summary)
        data = {
            "id": event.handoff_id,
            **summary,
            **_where(event.track.position),
            "track_id": event.track.track_id,
            "superseded_by": event.superseded_by,
            "battery": event.battery,
            "battery_lat": round(event.battery_position.lat_deg, 7),
            "battery_lon": round(event.battery_position.lon_deg, 7),
            "sidc": _BATTERY_SIDC,
            "range_m": _round(event.range_m, 0),
            "bearing_deg": _round(event.bearing_deg),
            "options": [
                {"effector": o.effector, "clear": o.deconfliction_clear} for o in event.options
            ],
            "nearest_blue_callsign": decon.nearest_blue_callsign,
            "nearest_blue_callsign_provenance": decon.nearest_blue_callsign_provenance,
            "nearest_blue_m": _round(decon.nearest_blue_m, 0),
            "operator_authorisation_required": True,
            "origin_node": event.origin_node,
            "revisions": list(revisions),
        }
        changes = self._upsert("cue", event.handoff_id, data)
        self._revisions[event.handoff_id] = revisions
        return changes

    def _order(self, event: FiveLineOrder) -> list[Change]:
        old = self._layers["order"].get(event.event_id)
        area = event.location
        corners = [(p.lat_deg, p.lon_deg) for p in area.polygon]
        if area.point is not None:
            lat, lon = area.point.lat_deg, area.point.lon_deg
        else:
            lat = sum(c[0] for c in corners) / len(corners)
            lon = sum(c[1] for c in corners) / len(corners)
        data = {
            **(old or {"status": "received", "check": None, "reason": None}),
            "id": event.event_id,
            "order_id": event.order_id,
            "source": event.source,
            "time": event.time.isoformat(),
            "airframe": event.airframe,
            "task": event.task.value,
            "priority": event.priority.value,
            "lat": round(lat, 7),
            "lon": round(lon, 7),
            "mgrs": area.mgrs,
            "polygon": [[round(a, 7), round(b, 7)] for a, b in corners],
            "origin_node": None,
        }
        return self._upsert("order", event.event_id, data)

    def _order_status(self, event: OrderStatus) -> list[Change]:
        # Another node's status is its own entity: order ids are the issuer's
        # (``slb-order-<id>``), so a remote status (or one forged on a remote's subjects) under
        # the id of this node's order must never rewrite that order's state here. Local ids
        # start with their system (``slb-``, ``sweccis-``, ``local-``), never ``node/``.
        key = (
            event.order_event_id
            if event.origin_node is None
            else f"node/{event.origin_node}/{event.order_event_id}"
        )
        old = self._layers["order"].get(key)
        data = (
            dict(old)
            if old is not None
            else {
                "id": key,
                "order_id": event.order_id,
                "source": event.source,
                "task": None,
                "priority": None,
                "lat": None,
                "lon": None,
                "mgrs": None,
                "polygon": [],
            }
        )
        data.update(
            time=event.time.isoformat(),
            airframe=event.airframe or data.get("airframe"),
            status=event.status.value,
            check=event.check,
            reason=event.reason,
            origin_node=event.origin_node,
        )
        return self._upsert("order", key, data)

    def _detection(self, event: Detection) -> list[Change]:
        data = {
            "id": event.event_id,
            "time": event.time.isoformat(),
            **_where(event.position),
            "airframe": event.airframe,
            "sensor": event.sensor.value,
            "object_class": event.object_class,
            "subtype": event.subtype,
            "confidence": round(event.confidence, 3),
            "sigma_h_m": _round(event.sigma_h_m),
            "origin_node": event.origin_node,
        }
        return self._upsert("detection", event.event_id, data)


_HANDLERS: Mapping[type, Callable[[Picture, Any], list[Change]]] = {
    Telemetry: Picture._telemetry,
    LinkState: Picture._link_state,
    Track: Picture._track,
    BlueForce: Picture._blue,
    Handoff: Picture._handoff,
    FiveLineOrder: Picture._order,
    OrderStatus: Picture._order_status,
    Detection: Picture._detection,
}


def entity_count(snapshot: Mapping[str, Iterable[Mapping[str, Any]]], layers: Iterable[str]) -> int:
    """How many entities of ``layers`` have a position (what the page draws a symbol for)."""
    return sum(1 for layer in layers for e in snapshot.get(layer, ()) if e.get("lat") is not None)
