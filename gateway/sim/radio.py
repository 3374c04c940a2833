"""The simulated airframe's AD9361 radio: answers hop schedules and reports its hops.

``SimRadio.answer`` takes a FISCHER_HOP_SCHEDULE addressed to the airframe and returns the
FISCHER_HOP_SCHEDULE_ACK to send: ACCEPTED for a plan the radio can fly, an UNSUPPORTED_*
result for one it cannot (a frequency outside 70 MHz to 6 GHz or an unused slot count, a
bandwidth over 56 MHz, a dwell under ``min_dwell_ns``), or the forced ``result`` the
operator chose (``simulate --hop-result``). ``ignore_first`` drops the first schedules
unanswered, as a lost uplink or a lost ACK would. ``events_at`` gives the FISCHER_HOP_EVENTs
due: while a schedule is active, one per call, sampled from the schedule (every fourth a
hop away from a reactive jammer). No I/O and no clock of its own: callers pass UNIX time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from gateway.domain.hopping import AD9361_MAX_BW_HZ, AD9361_RANGE_HZ, FASTLOCK_SLOTS
from gateway.fleet.hopdialect import (
    HOP_RESULT_ACCEPTED,
    HOP_RESULT_UNSUPPORTED_BANDWIDTH,
    HOP_RESULT_UNSUPPORTED_DWELL,
    HOP_RESULT_UNSUPPORTED_FREQUENCY,
    POWER_UNKNOWN_DBM,
    FischerHopEvent,
    FischerHopSchedule,
    FischerHopScheduleAck,
)

__all__ = ["SimRadio"]

_REASON_SCHEDULED, _REASON_JAMMED = 0, 1
#: Every this many reports, the simulated jammer catches a channel and the radio hops away.
_JAM_EVERY = 4


@dataclass
class SimRadio:
    """The radio of airframe ``sysid``; see the module docstring."""

    sysid: int
    component: int = 1
    result: int | None = None
    """Answer every schedule with this FISCHER_HOP_SCHEDULE_RESULT (None: check the plan)."""
    ignore_first: int = 0
    """Schedules left unanswered before the first answer."""
    min_dwell_ns: int = 500
    schedules: list[int] = field(default_factory=list)
    """The schedule id of every FISCHER_HOP_SCHEDULE for us that arrived."""
    active: FischerHopSchedule | None = None
    started_unix_s: float = 0.0
    reports: int = 0

    @property
    def active_id(self) -> int:
        """The schedule hopped on, 0 for none."""
        return 0 if self.active is None else int(self.active.schedule_id)

    def answer(self, msg: FischerHopSchedule, now_unix_s: float) -> FischerHopScheduleAck | None:
        """The answer to ``msg`` (None: not for us, or ignored on purpose)."""
        if msg.target_system != self.sysid or msg.target_component not in (0, self.component):
            return None
        self.schedules.append(int(msg.schedule_id))
        if len(self.schedules) <= self.ignore_first:
            return None
        result = self.check(msg) if self.result is None else self.result
        if result == HOP_RESULT_ACCEPTED and msg.schedule_id != self.active_id:
            self.active = msg
            self.started_unix_s = max(now_unix_s, msg.start_time_usec / 1e6)
        return FischerHopScheduleAck(
            msg.schedule_id, self.active_id, msg.get_srcSystem(), msg.get_srcComponent(), result
        )

    def check(self, msg: FischerHopSchedule) -> int:
        """ACCEPTED if this radio can fly ``msg``, else the UNSUPPORTED_* result saying why."""
        low, high = AD9361_RANGE_HZ
        used = list(msg.frequencies[: msg.slot_count])
        if not 1 <= msg.slot_count <= FASTLOCK_SLOTS or not all(low <= f <= high for f in used):
            return HOP_RESULT_UNSUPPORTED_FREQUENCY
        if not 0 < msg.bandwidth <= AD9361_MAX_BW_HZ:
            return HOP_RESULT_UNSUPPORTED_BANDWIDTH
        if msg.dwell < self.min_dwell_ns:
            return HOP_RESULT_UNSUPPORTED_DWELL
        return HOP_RESULT_ACCEPTED

    def events_at(self, unix_s: float) -> list[FischerHopEvent]:
        """One hop report at UNIX time ``unix_s`` while a schedule is active, else none."""
        plan = self.active
        if plan is None:
            return []
        self.reports += 1
        # A forced ACCEPTED (--hop-result) takes any plan, even a 0 ns dwell or 0 slots.
        hop_period_s = max(plan.dwell + plan.settle, 1) * 1e-9
        hops = max(1, int(max(unix_s - self.started_unix_s, 0.0) / hop_period_s)) % (1 << 32)
        slot = hops % min(max(plan.slot_count, 1), FASTLOCK_SLOTS)
        jammed = self.reports % _JAM_EVERY == 0
        return [
            FischerHopEvent(
                round(unix_s * 1e6),
                plan.frequencies[slot],
                plan.schedule_id,
                hops,
                slot,
                _REASON_JAMMED if jammed else _REASON_SCHEDULED,
                -58 - slot,
                -27 if jammed else POWER_UNKNOWN_DBM,
            )
        ]
