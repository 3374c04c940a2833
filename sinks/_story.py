"""The console's ``story`` format: what happened, in the words of the operation, not per event.

``Story.tell(event)`` returns the lines an event adds to the story, or none: a friendly unit
when first registered, the first detection of each airframe, sensor and class (later ones are
only counted), a track when created, when its fused class or confidence changes and when
lost, and each counter-UAS cue with its deconfliction. A callsign (peer text) is shown made
safe, quoted and marked with its provenance (``gateway.domain.peertext``). Positions are
MGRS. State is bounded: at most ``MAX_KEYS`` remembered keys per kind, the oldest forgotten
first.
"""

from __future__ import annotations

from collections import OrderedDict
from datetime import UTC

from gateway.domain.geodesy import to_mgrs
from gateway.domain.peertext import marked, safe_text, shown
from gateway.errors import GatewayError
from gateway.events import BlueForce, Deconfliction, Detection, Event, Handoff, Position, Track

__all__ = ["Story", "nearest_blue"]

MAX_KEYS = 10_000


def _mgrs(position: Position) -> str:
    try:
        return to_mgrs(position.lat_deg, position.lon_deg, 10, spaced=True)
    except GatewayError:  # polar: MGRS has no UTM zone there
        return f"{position.lat_deg:.5f},{position.lon_deg:.5f}"


def nearest_blue(check: Deconfliction) -> str:
    """The nearest friendly unit, its callsign (peer text) marked with its provenance."""
    if check.nearest_blue_callsign:
        return marked(
            check.nearest_blue_callsign,
            check.nearest_blue_callsign_provenance,
            check.nearest_blue_source,
        )
    provenance = check.nearest_blue_provenance
    return (
        f'uid "{safe_text(check.nearest_blue_uid or "?", 64)}"'
        f" ({'unknown provenance' if provenance is None else provenance.value}"
        f", source {check.nearest_blue_source or '-'})"
    )


class _Seen:
    def __init__(self) -> None:
        self._keys: OrderedDict[str, str] = OrderedDict()

    def changed(self, key: str, value: str) -> bool:
        """True when ``key`` is new or its value differs from the last one seen."""
        if self._keys.get(key) == value:
            return False
        self._keys[key] = value
        self._keys.move_to_end(key)
        while len(self._keys) > MAX_KEYS:
            self._keys.popitem(last=False)
        return True


class Story:
    """See the module docstring."""

    def __init__(self) -> None:
        self._blue = _Seen()
        self._detections = _Seen()
        self._tracks = _Seen()

    def tell(self, event: Event) -> list[str]:
        """The story lines ``event`` adds (often none)."""
        if isinstance(event, BlueForce):
            if not self._blue.changed(event.uid, ""):
                return []
            uid = safe_text(event.uid, 64)
            if event.callsign:
                who = shown(event.callsign, event.provenance, event.source, event.source_name)
                who += f', uid "{uid}",'
            else:
                who = f'uid "{uid}" ({event.provenance.value}, source {event.source_name or "-"})'
            return [f"blue force registered: {who} at {_mgrs(event.position)} via {event.source}"]
        if isinstance(event, Detection):
            key = f"{event.airframe}\x00{event.sensor.value}\x00{event.object_class}"
            if not self._detections.changed(key, ""):
                return []
            return [
                f"detection ingested: {event.airframe} {event.sensor.value.upper()} sees"
                f" {event.object_class} {event.subtype or ''} conf {event.confidence:.2f}"
                f" at {_mgrs(event.position)} ±{event.sigma_h_m:.0f} m".replace("  ", " ")
            ]
        if isinstance(event, Track):
            return self._track(event)
        if isinstance(event, Handoff):
            return self._handoff(event)
        return []

    def _track(self, track: Track) -> list[str]:
        if track.status == "lost":
            # The line is stamped with the time it was lost, to the second: the silence is
            # given as a duration, so a track lost within a second of its last detection
            # does not read "no detection since" the very second on the line.
            silent_s = max((track.time - track.last_seen).total_seconds(), 0.0)
            last = track.last_seen.astimezone(UTC).strftime("%H:%M:%S.%f")[:-5]
            return [
                f"track {track.track_id} lost: no detection for {silent_s:.1f} s"
                f" (the last at {last}Z)"
            ]
        if track.status == "merged":
            return [
                f"track {track.track_id} merged into {track.merged_into}:"
                " a second track of the same object"
            ]
        sensors = "+".join(sorted({s.value.upper() for s in track.sensors})) or "-"
        summary = f"{track.object_class}|{track.confidence:.2f}|{sensors}"
        if not self._tracks.changed(track.track_id, summary):
            return []
        verb = "created" if track.status == "created" else "fused"
        motion = ""
        if track.speed_mps is not None and track.course_deg is not None:
            motion = f", {track.speed_mps:.0f} m/s course {track.course_deg:03.0f}°"
        return [
            f"track {track.track_id} {verb}: {track.object_class} {track.subtype or ''}"
            f" confidence {track.confidence:.2f} (conflict {track.class_conflict:.2f})"
            f" from {sensors} of {', '.join(track.airframes) or '-'}"
            f" at {_mgrs(track.position)} CEP50 {track.cep50_m:.0f} m{motion}".replace("  ", " ")
        ]

    @staticmethod
    def _handoff(handoff: Handoff) -> list[str]:
        if handoff.status != "active":
            return [
                f"GUTE II cue {handoff.handoff_id} revision {handoff.revision}"
                f" {handoff.status} at battery {handoff.battery}"
                + (f" by {handoff.superseded_by}" if handoff.superseded_by else "")
                + (f": {handoff.note}" if handoff.note else "")
            ]
        check = handoff.deconfliction
        if check.nearest_blue_m is None:
            nearest = f"no friendly unit known ({check.blue_units_considered} considered)"
        else:
            nearest = f"nearest blue {nearest_blue(check)} at {check.nearest_blue_m:.0f} m"
        verdict = "deconfliction clear" if check.clear else "deconfliction NOT clear"
        if not check.blue_picture_complete:
            nearest += "; blue-force picture incomplete (no friendly position, or reports dropped)"
        advice = handoff.recommended_effector or "none (deconfliction not clear)"
        held = [o.effector for o in handoff.options if not o.deconfliction_clear]
        return [
            f"{verdict} for track {handoff.track.track_id}: {nearest}"
            + (f"; inside danger close of {', '.join(held)}" if held else ""),
            f"GUTE II cue: track {handoff.track.track_id} to battery {handoff.battery}"
            f" ({handoff.range_m:.0f} m from it, bearing {handoff.bearing_deg:03.0f}°),"
            f" recommended effector {advice}; the battery's operator decides",
        ]
