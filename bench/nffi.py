"""NFFI benchmark: our encoder and hostile-input parser against lxml on the same tracks.

Reproducible: ``python bench/nffi.py`` (``--help`` for options). Prints a Markdown table.

The same pre-built ``Telemetry`` events (``--tracks`` per document, ``--documents`` of them)
are, in the same run:

* **encode**: ``sinks.nffi.codec`` (``tracks_of`` + ``encode_message``: strings, every value
  fitted to the schema) against **lxml** building the same elements with ``SubElement`` and
  serialising them (the peer: a C tree builder, no fitting);
* **decode**: ``parse_message`` (defusedxml with DTDs and entities refused, every track
  checked and converted) against **lxml** ``fromstring`` alone (the peer: parsing without any
  check), both on the documents our encoder wrote;
* **split**: ``MessageSplitter`` cutting the documents back to back from 1400-byte chunks.

The ratio is ours over the peer in tracks per second (above 1: faster than the peer).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta

from lxml import etree

from gateway.events import Event, Position, Telemetry, Velocity
from sinks.nffi.codec import NAMESPACE, NffiOptions, encode_message, parse_message, tracks_of
from sinks.nffi.stream import MessageSplitter

T0 = datetime(2026, 11, 25, 12, 0, tzinfo=UTC)
OPTS = NffiOptions(system="FISCHER-GW", country="SWE", sec_classification="UNCLASSIFIED")


def make_batches(documents: int, tracks: int) -> list[list[Event]]:
    return [
        [
            Telemetry(
                event_id=f"t-{d}-{t}",
                airframe=f"F26E-{t:03d}",
                time=T0 + timedelta(seconds=d),
                position=Position(lat_deg=58.41 + t * 1e-4, lon_deg=15.62, alt_msl_m=600.0),
                velocity=Velocity(north_mps=10.0, east_mps=20.0, down_mps=0.0),
                mav_type=1,
            )
            for t in range(tracks)
        ]
        for d in range(documents)
    ]


def lxml_encode(batch: list[Event]) -> bytes:
    q = f"{{{NAMESPACE}}}"
    root = etree.Element(q + "NFFIMessage", nsmap={None: NAMESPACE})
    for event in batch:
        if not isinstance(event, Telemetry) or event.position is None or event.velocity is None:
            continue  # make_batches builds none such
        track = etree.SubElement(root, q + "track")
        pos = etree.SubElement(track, q + "positionalData", secClassification="UNCLASSIFIED")
        source = etree.SubElement(pos, q + "trackSource")
        system = etree.SubElement(source, q + "sourceSystem")
        etree.SubElement(system, q + "country").text = "SWE"
        etree.SubElement(system, q + "system").text = "FISCHER-GW"
        etree.SubElement(source, q + "transponderId").text = event.airframe
        etree.SubElement(pos, q + "dateTime").text = event.time.strftime("%Y%m%d%H%M%S")
        coordinates = etree.SubElement(pos, q + "coordinates")
        etree.SubElement(coordinates, q + "latitude").text = repr(event.position.lat_deg)
        etree.SubElement(coordinates, q + "longitude").text = repr(event.position.lon_deg)
        etree.SubElement(coordinates, q + "altitude").text = repr(event.position.alt_msl_m)
        etree.SubElement(pos, q + "bearing").text = "63.4"
        etree.SubElement(pos, q + "speed").text = repr(event.velocity.east_mps * 3.6)
        ident = etree.SubElement(track, q + "identificationData")
        etree.SubElement(ident, q + "unitSymbol").text = "SFAPMFQ--------"
        etree.SubElement(ident, q + "unitShortName").text = event.airframe
    return bytes(etree.tostring(root, xml_declaration=True, encoding="UTF-8"))


def timed(run: Callable[[], object], repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        started = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - started)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--documents", type=int, default=200)
    parser.add_argument("--tracks", type=int, default=20, help="tracks per document")
    parser.add_argument("--repeat", type=int, default=5, help="best of this many runs")
    args = parser.parse_args()
    batches = make_batches(args.documents, args.tracks)
    ours = [encode_message(tracks_of(b, OPTS)) for b in batches]
    stream = b"".join(ours)
    total = args.documents * args.tracks

    def split() -> None:
        splitter = MessageSplitter(1 << 20)
        for i in range(0, len(stream), 1400):
            splitter.feed(stream[i : i + 1400])

    rows = [
        (
            "encode",
            timed(lambda: [encode_message(tracks_of(b, OPTS)) for b in batches], args.repeat),
            timed(lambda: [lxml_encode(b) for b in batches], args.repeat),
        ),
        (
            "decode",
            timed(lambda: [parse_message(d) for d in ours], args.repeat),
            timed(lambda: [etree.fromstring(d) for d in ours], args.repeat),
        ),
        ("split", timed(split, args.repeat), None),
    ]
    print(
        f"{platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"lxml {etree.__version__}; {args.documents} documents of {args.tracks} tracks, "
        f"best of {args.repeat}, {datetime.now(UTC):%Y-%m-%d}"
    )
    print()
    print("| step | ours (tracks/s) | lxml peer (tracks/s) | ratio ours/peer |")
    print("|---|---:|---:|---:|")
    for step, ours_s, peer_s in rows:
        peer = "-" if peer_s is None else f"{total / peer_s:,.0f}"
        ratio = "-" if peer_s is None else f"{peer_s / ours_s:.2f}"
        print(f"| {step} | {total / ours_s:,.0f} | {peer} | {ratio} |")


if __name__ == "__main__":
    main()
