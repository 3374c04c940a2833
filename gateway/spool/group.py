"""One group commit of the spool: the writes of one loop pass, committed (or not) together.

The spool opens a ``Commit`` with the first write of a loop pass (an event appended by the
bus, a detection id remembered by the intake, a sink's confirmation or dead letter) and every
later write of the pass joins it; it commits once, at the end of the pass, or earlier when
someone needs it committed (a sink runner about to send what was appended, an explicit
``Spool.batch()`` scope ending). Whoever must act only once the writes are durable (the
detection acknowledgements) asks ``when_done`` and hears whether they committed. A group of
confirmations and dead letters alone, that no one waits on, lingers a little longer
(``gateway.spool.store.SETTLE_LINGER_S``) so the runners of one publish whose sinks answer in
different passes share its commit; an append or a listener joining it ends the linger.

A group also holds the rows it has yet to write: the events appended in the pass, each with
the bits of the sinks it is owed to, are inserted together (one ``executemany``) before the
next other statement or the commit, and the events whose last sink confirmed them are
deleted once, at the commit.
The record kept here is what undoing a group that did not commit takes: the ``seq`` of each
event appended in it (never to be sent) and the change it made to each sink's owed count.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import structlog

__all__ = ["Commit"]

log = structlog.get_logger(__name__)


class Commit:
    """The open group of writes of one spool, until it commits or rolls back."""

    __slots__ = (
        "_callbacks",
        "appended",
        "committed",
        "confirmed",
        "events",
        "lingered",
        "lingering",
        "on_hurry",
        "owed",
        "scheduled",
    )

    def __init__(self) -> None:
        #: ``seq`` and sinks of each event appended in this group.
        self.appended: list[tuple[int, tuple[str, ...]]] = []
        #: ``events`` rows appended and not written yet (their last field: the owed bits).
        self.events: list[tuple[int, str, str, bytes, float, int]] = []
        #: ``seq`` of events confirmed by a sink in this group: deleted at the commit if no
        #: other sink is owed them.
        self.confirmed: set[int] = set()
        #: What this group changed in each sink's owed count.
        self.owed: Counter[str] = Counter()
        #: None while open; True once committed, False once rolled back.
        self.committed: bool | None = None
        #: True if the end of the loop pass commits it (else its owner or the next flush).
        self.scheduled = False
        #: True while it waits past the end of its pass for more confirmations.
        self.lingering = False
        #: True once it has lingered (it lingers once at most).
        self.lingered = False
        #: Called by ``hurry`` while lingering (set by the spool).
        self.on_hurry: Callable[[Commit], None] | None = None
        self._callbacks: list[Callable[[bool], None]] = []

    @property
    def has_appends(self) -> bool:
        """True if events were appended in this group (not to be sent before it commits)."""
        return bool(self.appended)

    @property
    def waited_on(self) -> bool:
        """True if someone waits to hear how it ends."""
        return bool(self._callbacks)

    def hurry(self) -> None:
        """It must commit at the end of this pass after all: end its linger."""
        if self.lingering:
            self.lingering = False
            if self.on_hurry is not None:
                self.on_hurry(self)

    def when_done(self, callback: Callable[[bool], None]) -> None:
        """Call ``callback(committed)`` when the group ends (at once if it has ended)."""
        if self.committed is None:
            self._callbacks.append(callback)
            self.hurry()
        else:
            callback(self.committed)

    def end(self, committed: bool) -> None:
        """The group committed (True) or rolled back (False): tell those who asked."""
        self.committed = committed
        callbacks, self._callbacks = self._callbacks, []
        for callback in callbacks:
            try:
                callback(committed)
            except Exception:  # one listener's bug must not cost the others their answer
                log.exception("spool_commit_listener_failed")
