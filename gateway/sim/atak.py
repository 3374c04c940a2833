"""A simulated ATAK device for the demo: CoT events over UDP, read as ATAK reads them.

``SimulatedAtak`` owns a UDP socket on 127.0.0.1 (``port``) and parses each datagram as a
CoT XML event with defusedxml: uid, type, how, point, callsign, the remarks and the
gateway's ``__symbol`` element (its 2525C and 2525D codes). The first event of each uid,
``CotSeen``, goes to ``on_cot``; later ones of a uid are only counted. Datagrams that are
not CoT XML are counted in ``unreadable`` and skipped. At most ``MAX_UIDS`` uids are
remembered.
"""

from __future__ import annotations

import socket
from collections.abc import Callable
from dataclasses import dataclass

import anyio
import anyio.abc
from defusedxml import ElementTree

__all__ = ["MAX_UIDS", "CotSeen", "SimulatedAtak", "read_cot"]

MAX_UIDS = 10_000


@dataclass(frozen=True, slots=True)
class CotSeen:
    """What ATAK read from one CoT event."""

    uid: str
    type: str
    how: str
    lat: str
    lon: str
    hae: str
    callsign: str
    remarks: str
    sidc_2525c: str
    sidc_2525d: str


def read_cot(data: bytes) -> CotSeen | None:
    """The ``CotSeen`` of one CoT XML event, or None when ``data`` is not one."""
    try:
        root = ElementTree.fromstring(data)
    except (ElementTree.ParseError, ValueError):  # defusedxml's refusals are ValueErrors
        return None
    if root.tag != "event" or not root.get("uid"):
        return None
    point = root.find("point")
    detail = root.find("detail")
    contact = detail.find("contact") if detail is not None else None
    symbol = detail.find("__symbol") if detail is not None else None
    return CotSeen(
        uid=root.get("uid", ""),
        type=root.get("type", ""),
        how=root.get("how", ""),
        lat=point.get("lat", "") if point is not None else "",
        lon=point.get("lon", "") if point is not None else "",
        hae=point.get("hae", "") if point is not None else "",
        callsign=contact.get("callsign", "") if contact is not None else "",
        remarks=(detail.findtext("remarks") or "") if detail is not None else "",
        sidc_2525c=symbol.get("sidc2525c", "") if symbol is not None else "",
        sidc_2525d=symbol.get("sidc2525d", "") if symbol is not None else "",
    )


class SimulatedAtak:
    """See the module docstring; its loopback port is bound (``port``) when it is made."""

    def __init__(self, on_cot: Callable[[CotSeen], None]) -> None:
        self._on_cot = on_cot
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._socket.bind(("127.0.0.1", 0))
        self.port = int(self._socket.getsockname()[1])
        self.seen: set[str] = set()
        self.events = 0
        self.unreadable = 0

    async def serve(
        self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Read datagrams until cancelled."""
        udp = await anyio.abc.UDPSocket.from_socket(self._socket)
        task_status.started()
        async with udp:
            async for data, _ in udp:
                cot = read_cot(data)
                if cot is None:
                    self.unreadable += 1
                    continue
                self.events += 1
                if cot.uid in self.seen or len(self.seen) >= MAX_UIDS:
                    continue
                self.seen.add(cot.uid)
                self._on_cot(cot)
