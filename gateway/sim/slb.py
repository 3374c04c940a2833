"""A simulated SLB server for the demo: JC3IEDM object item reports over HTTPS.

A ``PostServer`` (loopback TLS, client certificate from the demo CA required) taking
``POST .../object-items``. Each new report is read as SLB would: the document's ``schema``
and ``event_id``, its object item (id, category, name), hostility and location; the
reading, ``SlbItem``, goes to ``on_item``. A document missing any of those is passed on as
unreadable (``problem`` says which part), never raised.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from gateway.sim.httpspost import PostServer
from gateway.sim.pki import DemoPki

__all__ = ["SimulatedSlb", "SlbItem", "read_item"]


@dataclass(frozen=True, slots=True)
class SlbItem:
    """What SLB read from one object item report."""

    schema: str
    event_id: str
    item_id: str
    category: str
    name: str
    hostility: str
    lat_deg: float
    lon_deg: float
    track_id: str | None
    problem: str = ""


def _text(value: object) -> str:
    return value if isinstance(value, str) else ""


def read_item(document: dict[str, Any]) -> SlbItem:
    """The ``SlbItem`` of ``document``; ``problem`` names the first part that is missing."""
    item = document.get("object_item") or {}
    location = document.get("location") or {}
    hostility = document.get("hostility_status") or {}
    track = (document.get("fischer") or {}).get("track") or {}
    problem = ""
    lat, lon = location.get("lat_coord"), location.get("long_coord")
    if not isinstance(lat, int | float) or not isinstance(lon, int | float):
        problem, lat, lon = "location", 0.0, 0.0
    if not isinstance(item, dict) or not _text(item.get("obj_item_id")):
        problem, item = "object_item", {}
    return SlbItem(
        schema=_text(document.get("schema")),
        event_id=_text(document.get("event_id")),
        item_id=_text(item.get("obj_item_id")),
        category=_text(item.get("cat_code")),
        name=_text(item.get("name_txt")),
        hostility=_text(hostility.get("code")) if isinstance(hostility, dict) else "",
        lat_deg=float(lat),
        lon_deg=float(lon),
        track_id=_text(track.get("track_id")) or None if isinstance(track, dict) else None,
        problem=problem,
    )


class SimulatedSlb(PostServer):
    """See the module docstring; its loopback port is bound (``port``) when it is made."""

    def __init__(self, pki: DemoPki, on_item: Callable[[SlbItem], None]) -> None:
        super().__init__(pki, lambda _path, document: on_item(read_item(document)))
