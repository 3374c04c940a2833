"""A simulated JAS 39 Gripen for the demo: its own position as NFFI 1.3 over TLS (IP1).

``fly_jas39`` connects to the gateway's NFFI source with the demo's client certificate (the
server's certificate checked against the demo CA) and sends one NFFI document a second, written
here as NFFI 1.3 describes it (docs/nffi.md), not with the gateway's codec: the aircraft's
track (``trackSource`` SWE / JAS39 / F21 / its transponder), a friendly fixed-wing fighter
(2525C ``SFAPMFF--------``) of F 21 at Luleå, on a straight line from Kallax towards Boden,
``speed`` times faster than real time. After its first document it calls ``on_sent`` once with
what it sent. It stops when cancelled; a refused or lost connection ends it with ``OSError`` or
an anyio stream error.
"""

from __future__ import annotations

import ssl
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime

import anyio

from gateway.clock import utc_now
from gateway.domain.geodesy import destination
from gateway.sim.pki import DemoPki

__all__ = ["CALLSIGN", "NAMESPACE", "SIDC", "Jas39Sent", "fly_jas39", "nffi_document"]

#: NFFI 1.3's namespace.
NAMESPACE = "urn:nato:fft:protocols:nffi13"

CALLSIGN = "GRIPEN 21"
#: The aircraft's transponder id and unit short name (NFFI identifiers have no spaces).
TRANSPONDER = "GRIPEN-21"
#: A friendly military fixed-wing fighter (MIL-STD-2525C).
SIDC = "SFAPMFF--------"
_KMH_PER_MPS = 3.6
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


def nffi_document(lat_deg: float, lon_deg: float, when: datetime) -> bytes:
    """One NFFI document holding the aircraft's track at (lat, lon) at ``when``."""
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<NFFIMessage xmlns="{NAMESPACE}"><track><positionalData>'
        "<trackSource><sourceSystem><country>SWE</country><system>JAS39</system>"
        f"<subsystem>F21</subsystem></sourceSystem><transponderId>{TRANSPONDER}</transponderId>"
        f"</trackSource><dateTime>{when.astimezone(UTC):%Y%m%d%H%M%S}</dateTime>"
        f"<coordinates><latitude>{lat_deg:.7f}</latitude><longitude>{lon_deg:.7f}</longitude>"
        f"<altitude>{_ALT_MSL_M:.0f}</altitude></coordinates>"
        f"<bearing>{_COURSE_DEG:.0f}</bearing><speed>{_SPEED_MPS * _KMH_PER_MPS:.0f}</speed>"
        f"</positionalData><identificationData><unitSymbol>{SIDC}</unitSymbol>"
        f"<unitShortName>{TRANSPONDER}</unitShortName></identificationData></track>"
        "</NFFIMessage>\n"
    ).encode()


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
            data = nffi_document(lat, lon, utc_now())
            await stream.send(data)
            if first:
                first = False
                on_sent(Jas39Sent(CALLSIGN, SIDC, lat, lon, _ALT_MSL_M, len(data)))
            await anyio.sleep(1.0)
