"""Each gateway event built and encoded once for all the CoT sinks that would send the same bytes.

Five CoT sinks routed the same detection used to build its ``CotEvent`` and encode its XML
five times. ``SharedBuilds`` keeps the most recent builds (``Encoded``: the event and its
encodings, each made at most once) for every CoT sink of the process. A build is reused only
when everything that shapes the bytes is the same:

- the event *object* (held by the entry and compared by identity, so a recycled ``id()`` never
  matches another event; events read back from the spool are new objects and are built anew);
- the sink's ``CotOptions`` (uid and callsign prefixes, stale times, symbology, geoid, group,
  version), interned by ``canonical`` so that equal options are one key;
- the CoT types of the airframes the event links to (a detection's reporting airframe, a
  track's airframes), which each sink learns from the telemetry it was given.

A telemetry event also teaches the sink its airframe's type; a reused build applies that to
the asking sink's map as ``build`` would have. Memory is bounded: at most ``size`` entries,
the oldest dropped first; a miss costs one build, as before.

``AirframeTypes`` is a sink's map of airframe → CoT type, bounded too: since the ``nats``
source, telemetry of any airframe id another node (or whoever may publish on its subjects)
names reaches the sink, so the map keeps the ``MAX_AIRFRAME_TYPES`` airframes heard from most
recently. A forgotten airframe's detections link with the default type until its next state.
"""

from __future__ import annotations

from gateway.events import Detection, Event, Telemetry, Track
from sinks.cot.codec import Encoded
from sinks.cot.event import CotOptions, build

__all__ = ["DEFAULT_SIZE", "MAX_AIRFRAME_TYPES", "SHARED", "AirframeTypes", "SharedBuilds"]

#: Builds kept: a few batches (``batch_max`` 100 by default) of every CoT sink in step.
DEFAULT_SIZE = 1024

#: Airframes whose CoT type a sink keeps (its own fleet is at most 255; remote nodes add theirs).
MAX_AIRFRAME_TYPES = 4096

#: The event, its build, and the (airframe, CoT type) a telemetry event teaches.
_Entry = tuple[Event, Encoded | None, tuple[str, str] | None]


def _links(event: Event, own_types: dict[str, str]) -> object:
    """The part of ``own_types`` that ``event``'s CoT depends on."""
    if isinstance(event, Detection):
        return own_types.get(event.airframe)
    if isinstance(event, Track):
        return tuple(own_types.get(airframe) for airframe in event.airframes)
    return None


class AirframeTypes(dict[str, str]):
    """Airframe → CoT type, the ``limit`` airframes set most recently (the oldest forgotten)."""

    def __init__(self, limit: int = MAX_AIRFRAME_TYPES) -> None:
        super().__init__()
        if limit < 1:
            raise ValueError(f"limit must be at least 1, got {limit}")
        self.limit = limit

    def __setitem__(self, airframe: str, cot_type: str) -> None:
        if airframe in self:
            del self[airframe]  # moved to the newest end
        super().__setitem__(airframe, cot_type)
        if len(self) > self.limit:
            del self[next(iter(self))]


class SharedBuilds:
    """The most recent ``size`` CoT builds, shared by the sinks whose options are equal."""

    def __init__(self, size: int = DEFAULT_SIZE) -> None:
        if size < 1:
            raise ValueError(f"size must be at least 1, got {size}")
        self.size = size
        self._entries: dict[tuple[int, int, object], _Entry] = {}
        self._options: dict[CotOptions, CotOptions] = {}
        #: Builds reused and made (for tests and benchmarks).
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._entries)

    def canonical(self, options: CotOptions) -> CotOptions:
        """The one instance of options equal to ``options`` (hashed once, at a sink's start)."""
        return self._options.setdefault(options, options)

    def encoded(
        self, event: Event, options: CotOptions, own_types: dict[str, str]
    ) -> Encoded | None:
        """``event`` built with ``options`` and ``own_types``, as ``Encoded`` (None: no CoT).

        ``options`` must come from ``canonical``. ``own_types`` is updated as ``build`` does.
        """
        key = (id(event), id(options), _links(event, own_types))
        entry = self._entries.get(key)
        if entry is not None and entry[0] is event:
            self.hits += 1
            if entry[2] is not None:
                airframe, own_type = entry[2]
                own_types[airframe] = own_type
            return entry[1]
        self.misses += 1
        cot = build(event, options, own_types)
        encoded = None if cot is None else Encoded(cot)
        taught = None
        if isinstance(event, Telemetry):
            taught = (event.airframe, own_types[event.airframe])
        entries = self._entries
        if key in entries:
            del entries[key]  # an older event under a recycled id(): replaced below
        elif len(entries) >= self.size:
            del entries[next(iter(entries))]
        entries[key] = (event, encoded, taught)
        return encoded


#: The builds every CoT sink of this process shares.
SHARED = SharedBuilds()
