"""A simulated JAS 39 Gripen for the demo: its own position as NFFI 1.3 over TLS (IP1).

``fly_jas39`` connects to the gateway's NFFI source with the demo's client certificate
(the server's certificate checked against the demo CA) and sends one NFFI document a
second, written with the NFFI integration's codec (``sinks.nffi.codec``): the aircraft's
track, a friendly fixed-wing fighter (2525C ``SFAPMFF--------``) of F 21 at Luleå, on a
straight line from Kallax towards Boden, ``speed`` times faster than real time. After its
first document it calls ``on_sent`` once with what it sent. It stops when cancelled; a
refused or lost connection ends it with ``OSError`` or an anyio stream error.
"""

from __future__ import annotations

import math
import ssl
from collections.abc import Callable
from dataclasses import dataclass

import anyio

from gateway.clock import utc_now
from gateway.domain.geodesy import destination
from gateway.events import BlueForce, Position, Provenance
from gateway.sim.pki import DemoPki
from sinks.nffi.codec import NffiOptions, encode_message, encode_track

__all__ = ["CALLSIGN", "SIDC", "Jas39Sent", "fly_jas39"]

CALLSIGN = "GRIPEN 21"
#: A friendly military fixed-wing fighter (MIL-STD-2525C).
SIDC = "SFAPMFF--------"
_OPTIONS = NffiOptions(system="JAS39", country="SWE", subsystem="F21")
_START = (65.5438, 22.1219)  # Luleå-Kallax
_COURSE_DEG = 315.0
_SPEED_MPS = 230.0
_ALT_MSL_M = 4000.0


@dataclass(frozen=True, slots=True)
class Jas39Sent:
    """The first document sent: the aircraft's callsign, SIDC and where it was."""

    callsign: str
    sidc: str
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    bytes: int


def _position(elapsed_s: float) -> tuple[float, float]:
    lat, lon = destination(*_START, _COURSE_DEG, _SPEED_MPS * elapsed_s)
    return lat, lon


async def fly_jas39(
    host: str, port: int, pki: DemoPki, *, speed: float, on_sent: Callable[[Jas39Sent], None]
) -> None:
    """Send the aircraft's track to ``host:port`` once a second until cancelled."""
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=pki.ca_file)
    context.load_cert_chain(pki.client_cert, pki.client_key)
    stream = await anyio.connect_tcp(host, port, ssl_context=context, tls_standard_compatible=False)
    started = anyio.current_time()
    first = True
    async with stream:
        while True:
            elapsed_s = (anyio.current_time() - started) * speed
            lat, lon = _position(elapsed_s)
            event = BlueForce(
                event_id=f"jas39-{math.floor(elapsed_s)}",
                uid=CALLSIGN,
                time=utc_now(),
                callsign=CALLSIGN,
                position=Position(lat_deg=lat, lon_deg=lon, alt_msl_m=_ALT_MSL_M),
                source="sim",
                course_deg=_COURSE_DEG,
                speed_mps=_SPEED_MPS,
                sidc=SIDC,
                provenance=Provenance.AUTHENTICATED,
            )
            track = encode_track(event, _OPTIONS)
            assert track is not None  # noqa: S101 - a position is always there
            data = encode_message([track])
            await stream.send(data)
            if first:
                first = False
                on_sent(Jas39Sent(CALLSIGN, SIDC, lat, lon, _ALT_MSL_M, len(data)))
            await anyio.sleep(1.0)
