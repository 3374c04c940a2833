"""A simulated SWECCIS server for the demo: FAS documents over TLS, each acknowledged.

It listens on 127.0.0.1 with TLS and requires a client certificate from the demo CA. Its
framing is its own reading of the protocol (docs/sweccis.md): a 4-byte big-endian length, then
one XML document (at most ``MAX_FRAME`` bytes; more, and the connection is closed). Nothing
here comes from the gateway's SWECCIS code. The client's ``Register`` is answered
``Registered`` with the FAS it asked to publish; each data document after it is parsed with
defusedxml and answered ``Ack`` ``accepted`` (an id seen before: ``duplicate``; a document it
cannot read: ``rejected`` with the reason). What it read of each Intel document about a track,
``FasTrack``, goes to ``on_track``.
"""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass

import anyio
import anyio.abc
from anyio.streams.buffered import BufferedByteReceiveStream
from defusedxml import ElementTree as SafeET

from gateway.sim.pki import DemoPki
from gateway.sim.tlspeer import TlsPeer

__all__ = ["MAX_FRAME", "NAMESPACE", "FasTrack", "SimulatedSweccis"]

#: The FAS documents' namespace (docs/sweccis.md; the shipped XSD's target namespace).
NAMESPACE = "urn:fischer-gateway:sweccis:fas:1"

MAX_FRAME = 1024 * 1024
_HEADER = struct.Struct(">I")
_NS = f"{{{NAMESPACE}}}"
_MAX_IDS = 100_000


@dataclass(frozen=True, slots=True)
class FasTrack:
    """What the server read from an Intel document about a track."""

    doc_id: str
    client: str
    track_id: str
    status: str
    object_class: str
    subtype: str
    hostility: str
    confidence: str
    lat_deg: str
    lon_deg: str


def _document(root: str, **attributes: str) -> ET.Element:
    return ET.Element(root, {"xmlns": NAMESPACE, "version": "1", **attributes})


def _frame(element: ET.Element) -> bytes:
    data: bytes = ET.tostring(element, encoding="utf-8", xml_declaration=False)
    return _HEADER.pack(len(data)) + data


class SimulatedSweccis(TlsPeer):
    """See the module docstring; its loopback port is bound (``port``) when it is made."""

    def __init__(self, pki: DemoPki, on_track: Callable[[FasTrack], None]) -> None:
        super().__init__(pki)
        self._on_track = on_track
        self.ids: dict[str, None] = {}

    async def _connection(self, stream: anyio.abc.ByteStream) -> None:
        client = ""
        async with stream:
            buffered = BufferedByteReceiveStream(stream)
            try:
                while True:
                    (length,) = _HEADER.unpack(await buffered.receive_exactly(_HEADER.size))
                    if length > MAX_FRAME:
                        return
                    answer, client = self._answer(await buffered.receive_exactly(length), client)
                    await stream.send(_frame(answer))
            except (anyio.EndOfStream, anyio.IncompleteRead, anyio.BrokenResourceError):
                return

    def _answer(self, data: bytes, client: str) -> tuple[ET.Element, str]:
        try:
            root = SafeET.fromstring(data)
        except (SafeET.ParseError, ValueError) as exc:  # defusedxml's refusals are ValueErrors
            answer = _document("Ack", ref="unknown", status="rejected")
            ET.SubElement(answer, "Reason").text = f"not XML: {str(exc)[:200]}"
            return answer, client
        name = root.tag.removeprefix(_NS)
        doc_id = root.get("id", "")
        if name == "Register":
            answer = _document("Registered", ref=doc_id)
            for fas in root.findall(f"{_NS}Publish"):
                ET.SubElement(answer, "Publish").text = fas.text or ""
            return answer, root.findtext(f"{_NS}Client") or "?"
        if not client or not doc_id:
            return _document("Ack", ref=doc_id or "unknown", status="rejected"), client
        if doc_id in self.ids:
            return _document("Ack", ref=doc_id, status="duplicate"), client
        self.ids[doc_id] = None
        if len(self.ids) > _MAX_IDS:
            del self.ids[next(iter(self.ids))]
        track = root.find(f"{_NS}Track")
        if name == "Intel" and track is not None:
            position = track.find(f"{_NS}Position")
            self._on_track(
                FasTrack(
                    doc_id=doc_id,
                    client=client,
                    track_id=track.findtext(f"{_NS}TrackId") or "",
                    status=track.findtext(f"{_NS}Status") or "",
                    object_class=track.findtext(f"{_NS}Class") or "",
                    subtype=track.findtext(f"{_NS}Subtype") or "",
                    hostility=track.findtext(f"{_NS}Hostility") or "",
                    confidence=track.findtext(f"{_NS}Confidence") or "",
                    lat_deg=position.get("latDeg", "") if position is not None else "",
                    lon_deg=position.get("lonDeg", "") if position is not None else "",
                )
            )
        return _document("Ack", ref=doc_id, status="accepted"), client
