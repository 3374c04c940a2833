"""An airframe's store of unacknowledged detections, re-sent until the gateway acknowledges them.

Every FISCHER_DETECTION the airframe sends is held until a FISCHER_DETECTION_ACK with the same
identity (``detection_id``, ``time_usec``) and ``target_system`` equal to the airframe's
system id arrives. Each held detection is re-sent with jittered exponential backoff, and all
re-sends together leave at a capped rate, so a backlog from a long outage drains at that rate
instead of flooding the link when it returns. The store is bounded: when full, the oldest
detection is dropped and counted. Re-sending starts once the gateway has acknowledged any
detection at all, so a gateway without acknowledgements never receives re-sends (detections
are held from the first one). No I/O and no clock of its own: callers pass the time (real,
monotonic seconds) in. docs/detection-ack.md is the protocol an airframe implements.
"""

from __future__ import annotations

import heapq
import math
import random
from collections import OrderedDict
from dataclasses import dataclass, fields

from gateway.fleet.dialect import ACK_RESULT_NAMES, FischerDetection, FischerDetectionAck

__all__ = ["DetectionCounts", "ResendPolicy", "ResendStore"]

#: MAV_COMP_ID_ALL: an acknowledgement for every component of the target system.
_ALL_COMPONENTS = 0
#: Backoff stops doubling long before a float could overflow.
_MAX_DOUBLINGS = 60


@dataclass(frozen=True)
class ResendPolicy:
    """How unacknowledged detections are re-sent.

    Re-send ``n`` (1, 2, ...) of a detection leaves ``min(first_s × 2^(n-1), max_s) × f``
    after the previous send, ``f`` drawn uniformly from ``[1 - jitter, 1]``: never later than
    the nominal schedule, and spread so that detections lost together are not re-sent
    together. Re-sends are at least ``1 / rate_hz`` apart, whatever the backlog. The store
    holds at most ``capacity`` detections. With ``needs_ack_heard`` nothing is re-sent until
    the gateway has acknowledged some detection: one that does not acknowledge (an older
    gateway) would only receive duplicates. Raises ``ValueError`` naming a field out of range.
    """

    first_s: float = 1.0
    max_s: float = 8.0
    jitter: float = 0.2
    rate_hz: float = 20.0
    capacity: int = 10_000
    needs_ack_heard: bool = True

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not math.isfinite(value):
                expected = "a finite number"
            elif f.name in ("first_s", "rate_hz") and value <= 0:
                expected = "> 0"
            elif f.name == "max_s" and value < self.first_s:
                expected = f">= first_s ({self.first_s!r})"
            elif f.name == "jitter" and not 0 <= value < 1:
                expected = "in [0, 1)"
            elif f.name == "capacity" and (int(value) != value or value < 1):
                expected = "a whole number >= 1"
            else:
                continue
            raise ValueError(f"ResendPolicy.{f.name}: expected {expected}, got {value!r}")

    def nominal_s(self, attempt: int) -> float:
        """The un-jittered delay before re-send ``attempt`` (1 is the first re-send)."""
        doublings = min(max(attempt - 1, 0), _MAX_DOUBLINGS)
        return min(self.first_s * 2.0**doublings, self.max_s)

    def delay_s(self, attempt: int, draw: float) -> float:
        """The delay before re-send ``attempt`` for a uniform ``draw`` in [0, 1)."""
        return self.nominal_s(attempt) * (1.0 - self.jitter * draw)


@dataclass(slots=True)
class DetectionCounts:
    """What became of one airframe's detections."""

    sent: int = 0
    """Detections sent the first time."""
    resent: int = 0
    """Re-sends (a detection re-sent three times counts three)."""
    acknowledged: int = 0
    """Held detections an acknowledgement removed."""
    dropped: int = 0
    """Detections dropped unacknowledged because the store was full."""
    acks_unmatched: int = 0
    """Acknowledgements for nothing held: a second ack, or one after the detection was dropped."""
    acks_ignored: int = 0
    """Acknowledgements for another system or component, or with an unknown result."""


@dataclass(slots=True)
class _Held:
    message: FischerDetection
    attempts: int  # re-sends so far
    token: int  # the live heap entry's; older heap entries for this detection are stale


class ResendStore:
    """The unacknowledged detections of airframe ``sysid`` (component ``component``).

    ``policy`` None keeps nothing and re-sends nothing, but still counts. Not thread-safe;
    one task drives it. ``rng`` draws the jitter (seed it for a reproducible schedule).
    """

    def __init__(
        self,
        sysid: int,
        policy: ResendPolicy | None = None,
        *,
        component: int = 1,
        rng: random.Random | None = None,
    ) -> None:
        self.sysid = sysid
        self.component = component
        self.policy = policy
        self.counts = DetectionCounts()
        self._rng = rng if rng is not None else random.Random()  # noqa: S311 - jitter, not a secret
        self._held: OrderedDict[tuple[int, int], _Held] = OrderedDict()  # oldest first
        # (due_s, token, identity); entries whose token is no longer the held one are stale.
        self._due: list[tuple[float, int, tuple[int, int]]] = []
        self._tokens = 0
        self._next_allowed_s = -math.inf
        #: True once an acknowledgement for this airframe arrived: the gateway speaks them.
        self.has_heard_ack = False

    def __len__(self) -> int:
        """Detections held now, unacknowledged."""
        return len(self._held)

    def __contains__(self, identity: object) -> bool:
        """True if the detection ``(detection_id, time_usec)`` is held."""
        return identity in self._held

    def add(self, message: FischerDetection, now_s: float) -> None:
        """Hold ``message``, sent (the first time) at ``now_s``; drop the oldest if full."""
        self.counts.sent += 1
        if self.policy is None:
            return
        identity = (int(message.detection_id), int(message.time_usec))
        held = self._held.get(identity)
        if held is not None:  # the same detection sent again as new: one entry, one schedule
            held.message = message
            return
        while len(self._held) >= self.policy.capacity:
            self._held.popitem(last=False)
            self.counts.dropped += 1
        held = _Held(message, 0, 0)
        self._held[identity] = held
        self._schedule(self.policy, identity, held, now_s)

    def take_due(self, now_s: float) -> list[FischerDetection]:
        """The detections to re-send at ``now_s`` (at most what the rate cap allows), each
        rescheduled for its next re-send as if re-sent at ``now_s``."""
        policy = self.policy
        if policy is None or not self._may_resend(policy):
            return []
        spacing_s = 1.0 / policy.rate_hz
        out: list[FischerDetection] = []
        while self._due and self._next_allowed_s <= now_s:
            due_s, token, identity = self._due[0]
            held = self._held.get(identity)
            if held is None or held.token != token:
                heapq.heappop(self._due)
                continue
            if due_s > now_s:
                break
            heapq.heappop(self._due)
            out.append(held.message)
            held.attempts += 1
            self.counts.resent += 1
            self._next_allowed_s = now_s + spacing_s
            self._schedule(policy, identity, held, now_s)
        return out

    def next_due_s(self) -> float:
        """The earliest time ``take_due`` may return something (inf when nothing is held, or
        while re-sending waits for the gateway's first acknowledgement)."""
        if self.policy is None or not self._may_resend(self.policy):
            return math.inf
        while self._due:
            due_s, token, identity = self._due[0]
            held = self._held.get(identity)
            if held is not None and held.token == token:
                return max(due_s, self._next_allowed_s)
            heapq.heappop(self._due)
        return math.inf

    def acknowledge(self, ack: FischerDetectionAck) -> bool:
        """Stop re-sending the detection ``ack`` names; True if it was held.

        An acknowledgement for another system or component (other than 0, all components),
        or with a result this store does not know, is ignored and counted: an unknown result
        may mean something other than "stop".
        """
        is_ours = ack.target_system == self.sysid and ack.target_component in (
            _ALL_COMPONENTS,
            self.component,
        )
        if not is_ours or ack.result not in ACK_RESULT_NAMES:
            self.counts.acks_ignored += 1
            return False
        self.has_heard_ack = True
        if self._held.pop((int(ack.detection_id), int(ack.time_usec)), None) is None:
            self.counts.acks_unmatched += 1
            return False
        self.counts.acknowledged += 1
        if len(self._due) > 2 * len(self._held) + 64:
            self._compact()
        return True

    def _may_resend(self, policy: ResendPolicy) -> bool:
        return self.has_heard_ack or not policy.needs_ack_heard

    def _schedule(
        self, policy: ResendPolicy, identity: tuple[int, int], held: _Held, now_s: float
    ) -> None:
        self._tokens += 1
        held.token = self._tokens
        due_s = now_s + policy.delay_s(held.attempts + 1, self._rng.random())
        heapq.heappush(self._due, (due_s, held.token, identity))

    def _compact(self) -> None:
        # Acknowledged detections leave stale heap entries behind; rebuilding from the held
        # ones keeps the heap within a constant factor of the store's capacity.
        self._due = [entry for entry in self._due if self._is_live(entry)]
        heapq.heapify(self._due)

    def _is_live(self, entry: tuple[float, int, tuple[int, int]]) -> bool:
        held = self._held.get(entry[2])
        return held is not None and held.token == entry[1]
