"""A source's way onto the bus: ``SourcePublish``, refusing friendly reports under uids that
are not the source's to give."""

from __future__ import annotations

from collections.abc import Callable

import structlog

from gateway.events import BlueForce, Event, Extension
from gateway.ops.logsetup import RateLimit

__all__ = ["SourcePublish"]

log = structlog.get_logger(__name__)

_REFUSED_EVENT = {"pinned": "blue_force_pinned_uid_refused", "own": "blue_force_own_uid_refused"}


class SourcePublish:
    """A source's way onto the bus, refusing friendly reports under uids that are not theirs.

    A ``BlueForce`` whose ``uid`` a processor pins (``counter_uas`` ``blue_forces``) would
    otherwise reach every sink and draw the fixed unit wherever the report says (the registry
    ignores it, ATAK would not); one under the uid a sink gives our own airframe (an ``nffi``
    sink's trackSource read back: a C2 system echoing our tracks, or a forgery; a ``cot``
    sink's own-airframe uid heard back on a mesh the gateway also listens on) would make our
    airframe a second, "friendly" unit. Both are refused, counted (``pinned_refused``,
    ``own_refused`` on /status) and logged at most once per 10 s each.

    An ``Extension`` is refused too (``extension_refused``): only a processor that declared
    its type may publish one, and a source could otherwise name such a processor as its
    ``publisher`` and pass data no model has checked.
    """

    def __init__(
        self,
        source: str,
        pinned: frozenset[str],
        own: frozenset[str],
        publish: Callable[[Event], bool],
    ) -> None:
        self.source = source
        self.pinned = pinned
        self.own = own
        self.refused = {"pinned": 0, "own": 0, "extension": 0}
        self._publish = publish
        self._log_limit = RateLimit(interval_s=10.0)

    def __call__(self, event: Event) -> bool:
        if isinstance(event, Extension):
            self.refused["extension"] += 1
            if self._log_limit.allow("extension"):
                log.error(
                    "source_extension_refused",
                    source=self.source,
                    refused=self.refused["extension"],
                    note="only a processor that declares an extension type may publish it",
                )
            return False
        if isinstance(event, BlueForce):
            reason = (
                "pinned" if event.uid in self.pinned else "own" if event.uid in self.own else None
            )
            if reason is not None:
                self.refused[reason] += 1
                if self._log_limit.allow(reason):
                    # Our own reports heard back are routine on a CoT mesh the gateway both
                    # sends to and listens on: info, not a warning every 10 s for ever.
                    (log.warning if reason == "pinned" else log.info)(
                        _REFUSED_EVENT[reason],
                        source=self.source,
                        uid=event.uid,
                        refused=self.refused[reason],
                    )
                return False
        return self._publish(event)
