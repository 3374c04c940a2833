"""The demo's story: the operation's ten steps, each told once, in order, as its peer saw it.

``Narrator`` is fed what happened, from both sides of the wire: the gateway's own events (a
sink of the demo hands it every friendly unit, detection, track and cue the bus carries)
and what each stand-in parsed of what the gateway sent it (the GUTE II battery's cue, SLB's
object item, SWECCIS's Intel document, the Ra 180 net's message, ATAK's CoT). It tells:

1. the friendly units registered (the platoons' CoT position reports, parsed by the gateway);
2. the GUTE II battery registered, and the stand-in waiting for its cues;
3. the first detection of an inbound munition;
4. the featured track: the first munition fused from two sensors and cued with deconfliction
   clear;
5. its deconfliction with the nearest friendly unit;
6. its cue, once the battery acknowledged exactly that revision;
7. to 10. that track as SLB, SWECCIS, the Ra 180 net and ATAK received it (ATAK's with
   the 2525D code the gateway put on it; a CDM names no track, so the net's new-target
   message taken is the one nearest where SWECCIS or SLB first saw the track, within 1 km);

then, after step 10, the relay of a JAS 39's NFFI report to ATAK as a friendly unit, the
first cue held back because a friendly unit was too close, and the end. A step waits for
everything it names; steps come out in their order whatever order the wires answered in,
so a step is never told before its predecessors. ``missing()`` lists the steps never told.
Every store here is bounded (``MAX_KEPT``): the demo is short, the bound is for safety.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from gateway.clock import utc_now
from gateway.domain.geodesy import MgrsError, distance_bearing, from_mgrs, to_mgrs
from gateway.domain.peertext import marked, safe_text, shown
from gateway.errors import GatewayError
from gateway.events import BlueForce, Deconfliction, Detection, Event, Handoff, Position
from gateway.sim.atak import CotSeen
from gateway.sim.jas39 import Jas39Sent
from gateway.sim.ra180 import Heard
from gateway.sim.slb import SlbItem
from gateway.sim.sweccis import FasTrack

__all__ = ["MAX_KEPT", "STEPS", "Narrator"]

#: Observations kept per kind; the oldest are forgotten first.
MAX_KEPT = 10_000
#: The operation's steps, as numbered in the story.
STEPS = (
    "blue force registered",
    "GUTE II battery registered",
    "detections of inbound munitions ingested",
    "fused track",
    "deconfliction",
    "GUTE II cue",
    "SLB JC3IEDM object published",
    "SWECCIS FAS document dispatched",
    "Ra 180 CDM broadcast",
    "ATAK CoT",
)
_MUNITION = "loitering_munition"
#: A new target's Ra 180 message is taken as the featured track's when its grid reference is
#: within this distance of where SWECCIS or SLB first saw that track.
_SAME_TARGET_M = 1000.0
_INDENT = " " * 14


def _mgrs(position: Position) -> str:
    try:
        return to_mgrs(position.lat_deg, position.lon_deg, 10, spaced=True)
    except GatewayError:  # polar: MGRS has no UTM zone there
        return f"{position.lat_deg:.5f},{position.lon_deg:.5f}"


def _mgrs_of(lat: str | float, lon: str | float) -> str:
    try:
        return _mgrs(Position(lat_deg=float(lat), lon_deg=float(lon)))
    except ValueError:
        return f"{safe_text(str(lat), 20)},{safe_text(str(lon), 20)}"


def _plain(text: str, max_chars: int) -> str:
    """Peer text shown as printable ASCII (anything else as ``?``), cut to ``max_chars``."""
    return "".join(c if c.isascii() and c.isprintable() else "?" for c in text[:max_chars])


def _nearest(check: Deconfliction) -> str:
    if check.nearest_blue_m is None:
        return f"no friendly unit known ({check.blue_units_considered} considered)"
    who = (
        marked(
            check.nearest_blue_callsign,
            check.nearest_blue_callsign_provenance,
            check.nearest_blue_source,
        )
        if check.nearest_blue_callsign
        else f'uid "{safe_text(check.nearest_blue_uid or "?", 64)}"'
    )
    return f"nearest blue {who} at {check.nearest_blue_m:.0f} m"


V = TypeVar("V")


class _Kept(Generic[V]):
    """An insertion-ordered map that keeps the first value of a key, at most MAX_KEPT keys."""

    def __init__(self) -> None:
        self.items: OrderedDict[Any, V] = OrderedDict()

    def first(self, key: Any, value: V) -> None:
        if key in self.items:
            return
        self.items[key] = value
        while len(self.items) > MAX_KEPT:
            self.items.popitem(last=False)


class Narrator:
    """See the module docstring. ``write`` takes one line of the story (no newline)."""

    def __init__(self, write: Callable[[str], None], *, blue_units: int, voice: bool) -> None:
        self._write = write
        self._voice = voice
        self._blue_units = blue_units
        self._told = 0
        self._steps: dict[int, list[str]] = {}
        self._after: list[str] = []
        self._told_after: set[str] = set()
        self._blue: _Kept[BlueForce] = _Kept()
        self._battery: list[str] | None = None
        self._munition: Detection | None = None
        self._featured: Handoff | None = None
        self._held: Handoff | None = None
        self._cues: _Kept[dict[str, Any]] = _Kept()
        self._slb: _Kept[SlbItem] = _Kept()
        self._fas: _Kept[FasTrack] = _Kept()
        self._cot: _Kept[CotSeen] = _Kept()
        self._heard: _Kept[Heard] = _Kept()
        self._jas39: Jas39Sent | None = None
        self._relay: CotSeen | None = None

    # -- what happened ---------------------------------------------------------------------

    def battery(self, battery_id: str, position: Position, effectors: list[str], url: str) -> None:
        """The battery the counter-UAS processor cues, and its stand-in's address."""
        self._battery = [
            f"{battery_id} at {_mgrs(position)}, effectors {', '.join(effectors)}",
            f"confirmed: the GUTE II stand-in listens at {url} (TLS, client certificate of the"
            " demo CA required)",
        ]
        self._advance()

    def event(self, event: Event) -> None:
        """An event from the gateway's bus."""
        if isinstance(event, BlueForce) and event.source == "cot":
            self._blue.first(event.uid, event)
        elif isinstance(event, Detection) and event.object_class == _MUNITION:
            self._munition = self._munition or event
        elif isinstance(event, Handoff) and event.status == "active":
            track = event.track
            fused = track.object_class == _MUNITION and len(set(track.sensors)) >= 2
            if self._featured is None and fused and event.deconfliction.clear:
                self._featured = event
            if self._held is None and not event.deconfliction.clear:
                self._held = event
        self._advance()

    def cue_received(self, document: dict[str, Any]) -> None:
        """The GUTE II stand-in received a cue (its JSON document)."""
        self._cues.first((document.get("handoff_id"), document.get("revision")), document)
        self._advance()

    def slb_item(self, item: SlbItem) -> None:
        """The SLB stand-in read an object item report."""
        if item.track_id:
            self._slb.first(item.track_id, item)
        self._advance()

    def fas_track(self, track: FasTrack) -> None:
        """The SWECCIS stand-in read an Intel document about a track."""
        self._fas.first(track.track_id, track)
        self._advance()

    def heard(self, heard: Heard) -> None:
        """The Ra 180 stand-in heard a new target's message (and its announcement)."""
        if heard.cdm.type == "MAL" and heard.cdm.class_abbreviation == "LUFT-MUN":
            self._heard.first(heard.cdm.number, heard)
        self._advance()

    def cot(self, cot: CotSeen) -> None:
        """The ATAK stand-in read the first CoT event of a uid."""
        self._cot.first(cot.uid, cot)
        if self._relay is None and "NFFI" in cot.remarks:
            self._relay = cot
        self._advance()

    def jas39_sent(self, sent: Jas39Sent) -> None:
        """The simulated JAS 39 sent its first NFFI document."""
        self._jas39 = sent
        self._advance()

    # -- telling ---------------------------------------------------------------------------

    def missing(self) -> list[str]:
        """The steps not told (yet), as ``[n] name``."""
        return [f"[{n}] {STEPS[n - 1]}" for n in range(self._told + 1, len(STEPS) + 1)]

    def say(self, line: str) -> None:
        """A line outside the numbered steps (the opening, the end)."""
        self._write(f"{utc_now():%H:%M:%S}Z {line}")

    def _advance(self) -> None:
        self._compose()
        while self._told < len(STEPS) and self._told + 1 in self._steps:
            self._told += 1
            lines = self._steps[self._told]
            self.say(f"[{self._told}/{len(STEPS)}] {STEPS[self._told - 1]}: {lines[0]}")
            for line in lines[1:]:
                self._write(f"{_INDENT}{line}")
        if self._told == len(STEPS):
            for key, lines in self._afterwards():
                if key not in self._told_after:
                    self._told_after.add(key)
                    self.say(lines[0])
                    for line in lines[1:]:
                        self._write(f"{_INDENT}{line}")

    def _compose(self) -> None:
        steps = self._steps
        if (
            1 not in steps
            and self._blue.items
            and (len(self._blue.items) >= self._blue_units or self._featured is not None)
        ):
            steps[1] = self._step_blue()
        if 2 not in steps and self._battery is not None:
            steps[2] = self._battery
        if 3 not in steps and self._munition is not None:
            steps[3] = self._step_detection(self._munition)
        featured = self._featured
        if featured is None:
            return
        track = featured.track
        if 4 not in steps:
            sensors = "+".join(sorted(s.value.upper() for s in set(track.sensors)))
            steps[4] = [
                f"track {track.track_id} {track.object_class} {track.subtype}, confidence"
                f" {track.confidence:.2f} from {sensors} of {', '.join(track.airframes)} at"
                f" {_mgrs(track.position)} CEP50 {track.cep50_m:.0f} m",
                f"confirmed: the fusion processor published it, {track.detection_count}"
                " detections associated",
            ]
        if 5 not in steps:
            verdict = "clear" if featured.deconfliction.clear else "NOT clear"
            steps[5] = [
                f"{verdict} for track {track.track_id}: {_nearest(featured.deconfliction)}",
                f"confirmed: the counter-UAS processor considered"
                f" {featured.deconfliction.blue_units_considered} friendly units",
            ]
        cue = self._cues.items.get((featured.handoff_id, featured.revision))
        if 6 not in steps and cue is not None:
            steps[6] = [
                f"{featured.handoff_id} revision {featured.revision}: track {track.track_id}"
                f" to battery {featured.battery} ({featured.range_m:.0f} m from it, bearing"
                f" {featured.bearing_deg:03.0f}°), recommended effector"
                f" {featured.recommended_effector}; the battery's operator decides",
                f"confirmed: GUTE II battery {(cue.get('battery') or {}).get('id')} received it"
                f" over HTTPS: deconfliction"
                f" {'clear' if (cue.get('deconfliction') or {}).get('clear') else 'NOT clear'},"
                f" recommended {cue.get('recommended_effector') or 'none'},"
                f" operator_authorisation_required"
                f" {str(cue.get('operator_authorisation_required')).lower()}",
            ]
        item = self._slb.items.get(track.track_id)
        if 7 not in steps and item is not None:
            steps[7] = [
                f"object item {item.item_id} to SLB over HTTPS (client certificate)",
                f"confirmed: SLB parsed {safe_text(item.schema, 64)}: category {item.category},"
                f' "{safe_text(item.name, 64)}", hostility {item.hostility} at'
                f" {_mgrs_of(item.lat_deg, item.lon_deg)}",
            ]
        fas = self._fas.items.get(track.track_id)
        if 8 not in steps and fas is not None:
            steps[8] = [
                f"Intel document {fas.doc_id} to SWECCIS over TLS (client certificate)",
                f'confirmed: SWECCIS (client "{safe_text(fas.client, 64)}") acknowledged it and'
                f" parsed track {fas.track_id} {fas.status}: {fas.object_class} {fas.subtype}"
                f" {fas.hostility}, confidence {fas.confidence} at"
                f" {_mgrs_of(fas.lat_deg, fas.lon_deg)}",
            ]
        heard = self._heard_of(fas or item)
        if 9 not in steps and heard is not None:
            steps[9] = self._step_radio(heard, track.track_id)
        cot = next(
            (c for uid, c in self._cot.items.items() if uid.endswith(f"trk-{track.track_id}")),
            None,
        )
        if 10 not in steps and cot is not None:
            steps[10] = [
                f"CoT {cot.uid} type {cot.type} to ATAK over UDP",
                f"confirmed: ATAK parsed type {cot.type}, APP-6D (2525D) symbol code"
                f" {cot.sidc_2525d or '(none)'} (2525C {cot.sidc_2525c or '(none)'}), at"
                f" {_mgrs_of(cot.lat, cot.lon)} hae {cot.hae} m",
            ]

    def _heard_of(self, first: FasTrack | SlbItem | None) -> Heard | None:
        """The new-target message nearest where the track was first seen, if near enough."""
        if first is None:
            return None
        try:
            lat, lon = float(first.lat_deg), float(first.lon_deg)
        except ValueError:
            return None
        best: tuple[float, Heard] | None = None
        for heard in self._heard.items.values():
            try:
                cell = from_mgrs(heard.cdm.mgrs)
            except MgrsError:
                continue
            distance_m, _ = distance_bearing(lat, lon, cell.lat_deg, cell.lon_deg)
            if distance_m <= _SAME_TARGET_M and (best is None or distance_m < best[0]):
                best = (distance_m, heard)
        return None if best is None else best[1]

    def _step_blue(self) -> list[str]:
        units = list(self._blue.items.values())
        lines = [f"{len(units)} friendly units from their ATAK position reports"]
        for unit in units:
            who = shown(unit.callsign or unit.uid, unit.provenance, unit.source, unit.source_name)
            lines.append(f'{who}, uid "{safe_text(unit.uid, 64)}", at {_mgrs(unit.position)}')
        lines.append("confirmed: the gateway's CoT source parsed each report (CoT 2.0 XML, UDP)")
        return lines

    @staticmethod
    def _step_detection(detection: Detection) -> list[str]:
        return [
            f"{detection.airframe} {detection.sensor.value.upper()} sees {detection.object_class}"
            f" {detection.subtype} conf {detection.confidence:.2f} at {_mgrs(detection.position)}"
            f" ±{detection.sigma_h_m:.0f} m",
            f"confirmed: the gateway parsed it from {detection.airframe}'s MAVLink 2 stream in"
            " the AES-256-GCM tunnel",
        ]

    def _step_radio(self, heard: Heard, track_id: str) -> list[str]:
        cdm = heard.cdm
        lines = [
            f"new target NR {cdm.number:04d} (track {track_id}) to the Ra 180 net over UDP:"
            f" {heard.text}",
            f"confirmed: the radio gateway parsed {cdm.type} {cdm.hostility}"
            f" {cdm.class_abbreviation} at {cdm.mgrs}, confidence {cdm.confidence_pct} %",
        ]
        if heard.wav is not None:
            lines.append(
                f"voice: Swedish announcement {heard.wav.path.name},"
                f" {heard.wav.seconds:.1f} s at {heard.wav.rate_hz} Hz (espeak-ng)"
            )
        elif self._voice:
            lines.append("voice: no announcement rendered in time (see the gateway's log)")
        else:
            lines.append("voice: espeak-ng is not installed, so no Swedish WAV (text only)")
        return lines

    def _afterwards(self) -> list[tuple[str, list[str]]]:
        told: list[tuple[str, list[str]]] = []
        if self._jas39 is not None and self._relay is not None:
            sent, relay = self._jas39, self._relay
            told.append(
                (
                    "relay",
                    [
                        f'NFFI relay: JAS 39 "{sent.callsign}" sent its track as NFFI 1.3 over'
                        f" TLS ({sent.sidc}, {sent.alt_msl_m:.0f} m MSL at"
                        f" {_mgrs_of(sent.lat_deg, sent.lon_deg)})",
                        f"confirmed: ATAK parsed a friendly {relay.type}"
                        f' "{safe_text(relay.callsign, 64)}" uid {safe_text(relay.uid, 64)}'
                        f" ({_plain(relay.remarks, 80)})",
                    ],
                )
            )
        held = self._held
        if held is not None:
            cue = self._cues.items.get((held.handoff_id, held.revision))
            if cue is not None:
                told.append(
                    (
                        "held",
                        [
                            f"deconfliction NOT clear for track {held.track.track_id}:"
                            f" {_nearest(held.deconfliction)}",
                            f"GUTE II cue {held.handoff_id} revision {held.revision}: recommended"
                            " effector none (deconfliction not clear); the battery's operator"
                            " decides",
                            f"confirmed: GUTE II battery received revision {held.revision}"
                            " over HTTPS: deconfliction NOT clear, recommended"
                            f" {cue.get('recommended_effector') or 'none'}",
                        ],
                    )
                )
        return told
