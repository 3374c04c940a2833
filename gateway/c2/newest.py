"""The newest report time per unit, bounded: what keeps a source from going back in time.

A friendly-force source (CoT, NFFI) publishes a unit's position only when it is newer than
the last one it published for that unit; an older report is ``older`` and the same one again
``duplicate``. Only the ``max_uids`` units heard from most recently are remembered (the one
heard from longest ago is forgotten first), so a flood of invented uids costs bounded memory.
"""

from __future__ import annotations

from collections import OrderedDict
from datetime import datetime
from typing import Literal

__all__ = ["NewestTimes"]


class NewestTimes:
    """The newest accepted time of at most ``max_uids`` units."""

    def __init__(self, max_uids: int) -> None:
        self.max_uids = max_uids
        self._times: OrderedDict[str, datetime] = OrderedDict()

    def __len__(self) -> int:
        return len(self._times)

    def refusal(self, uid: str, time: datetime) -> Literal["older", "duplicate"] | None:
        """Why a report of ``uid`` at ``time`` is not news, or None if it is."""
        newest = self._times.get(uid)
        if newest is None or time > newest:
            return None
        return "older" if time < newest else "duplicate"

    def remember(self, uid: str, time: datetime) -> None:
        """``time`` is now the newest of ``uid``; forget the unit heard from longest ago."""
        self._times[uid] = time
        self._times.move_to_end(uid)
        while len(self._times) > self.max_uids:
            self._times.popitem(last=False)
