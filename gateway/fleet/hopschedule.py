"""Hop schedules in both directions: the plan uploaded to each airframe, its hops coming back.

Uplink: for every airframe with a ``hop_plan`` the gateway sends a FISCHER_HOP_SCHEDULE on
the airframe's session (its active link, in that link's security mode) once the airframe is
linked, i.e. heard with authenticated frames. It re-checks right before each send that the
AD9361 can fly the plan and that its dwell beats the configured reactive jammer. It re-sends
with doubling waits (``ack_timeout_s`` up to ``retry_max_s``) until a
FISCHER_HOP_SCHEDULE_ACK for that schedule id arrives. ACCEPTED ends the upload; DENIED and
FAILED are asked again after ``retry_max_s``; an UNSUPPORTED_* result is final for the plan
(the state says ``refused``). An airframe that later reports hops on another schedule (it
rebooted, or a link change brought back one that lost it) gets the plan again: at once the
first time, then with the same doubling waits while the losses keep coming, so nobody can
loop the upload.

Downlink: each FISCHER_HOP_EVENT becomes a ``HopEvent``. Every one is counted (metrics per
airframe and reason, hops flown from the hop counts); at most ``PUBLISH_RATE_HZ`` per
airframe and reason (bursts of ``PUBLISH_BURST``) are published, the rest counted as
dropped: a flood of hop reports costs counters, never memory, queue space or a log line each.
"""

from __future__ import annotations

import time
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

import anyio
import structlog

from gateway.clock import Clock
from gateway.config import HopPlanConfig
from gateway.domain.hopping import AD9361_RANGE_HZ, FASTLOCK_SLOTS, HopPlanError
from gateway.errors import FrameError, LinkError
from gateway.events import Event, HopEvent, HopReason, event_id
from gateway.fleet.hopdialect import (
    HOP_REASON_NAMES,
    HOP_RESULT_ACCEPTED,
    HOP_RESULT_DENIED,
    HOP_RESULT_FAILED,
    HOP_RESULT_NAMES,
    POWER_UNKNOWN_DBM,
    FischerHopSchedule,
)
from gateway.fleet.mavlink import MavMessage
from gateway.fleet.session import GATEWAY_COMPID, GATEWAY_SYSID, AirframeSession
from gateway.ops.instruments import Instruments
from gateway.ops.logsetup import RateLimit

__all__ = [
    "PUBLISH_BURST",
    "PUBLISH_RATE_HZ",
    "STATES",
    "HopSchedules",
    "HopUpload",
    "hop_schedule_message",
    "schedule_id",
]

log = structlog.get_logger(__name__)

#: Hop events published per airframe and reason per second at most, and the burst allowed.
PUBLISH_RATE_HZ = 5.0
PUBLISH_BURST = 10.0
#: The upload states, as /status and fg_hop_schedule_state show them.
STATES = ("waiting_link", "sent", "accepted", "refused", "retrying", "invalid")
#: How often an upload waiting for its airframe's link looks again, seconds.
LINK_POLL_S = 0.25
_TRANSIENT_RESULTS = frozenset({HOP_RESULT_DENIED, HOP_RESULT_FAILED})
_U32 = 1 << 32
_LOG_INTERVAL_S = 10.0
#: Schedules whose hop counters are remembered per airframe, so that reports of an old and a
#: new schedule arriving mixed count each hop once.
_SCHEDULES_COUNTED = 4


def schedule_id(config: HopPlanConfig) -> int:
    """The schedule id of a plan: CRC-32 of its wire values, never 0 (0 means "none")."""
    message = hop_schedule_message(config, 0, 0)
    values = (*message.frequencies, message.bandwidth, message.dwell, message.settle)
    crc = zlib.crc32(b",".join(str(v).encode() for v in values))
    return crc or 1


def hop_schedule_message(config: HopPlanConfig, target_system: int, sid: int) -> Any:
    """The FISCHER_HOP_SCHEDULE of ``config`` for ``target_system``, starting at once."""
    plan = config.plan()
    freqs = [round(f) for f in plan.frequencies_hz]
    return FischerHopSchedule(
        0,
        freqs + [0] * (FASTLOCK_SLOTS - len(freqs)),
        sid,
        round(plan.bandwidth_hz),
        max(1, round(plan.dwell_s * 1e9)),
        round(plan.settle_s * 1e9),
        target_system,
        0,
        len(freqs),
    )


@dataclass(slots=True)
class HopUpload:
    """One airframe's hop-schedule upload: its plan, its state and what the airframe said."""

    session: AirframeSession
    config: HopPlanConfig
    schedule_id: int
    state: str = "waiting_link"
    sends: int = 0
    last_result: str | None = None
    active_schedule_id: int | None = None
    """The schedule the airframe last said (ACK or hop event) it hops on."""
    accepted_mono: float | None = None
    answered: anyio.Event = field(default_factory=anyio.Event)
    answer: int | None = None
    is_awaiting: bool = False
    """True from a send until its first answer: only then is an answer taken."""
    link_lost: bool = False
    """Every link of the airframe went down since the schedule was accepted."""
    wake: anyio.Event = field(default_factory=anyio.Event)
    losses: int = 0
    """Times in a row the accepted schedule was lost (or re-verified): the backoff's step."""
    last_loss_mono: float | None = None
    resend_at_mono: float = 0.0
    """No upload before this (monotonic seconds): the backoff after a loss."""

    def lost(self) -> None:
        """The accepted schedule must be sent again: at once the first time, then after
        ``ack_timeout_s`` doubling up to ``retry_max_s`` while the losses keep coming (an
        airframe, or a stranger on an unsecured link, reporting other schedules must not
        loop the upload)."""
        now = time.monotonic()
        config = self.config
        quiet_s = 2.0 * config.retry_max_s + config.ack_timeout_s
        if self.last_loss_mono is None or now - self.last_loss_mono > quiet_s:
            self.losses = 0
        delay_s = 0.0
        if self.losses:
            delay_s = min(config.ack_timeout_s * 2.0 ** (self.losses - 1), config.retry_max_s)
        self.losses = min(self.losses + 1, 32)
        self.last_loss_mono = now
        self.resend_at_mono = now + delay_s
        self.state = "retrying" if delay_s else "sent"

    def answer_received(self) -> int | None:
        """The result the airframe answered the last send with, None if none came yet."""
        return self.answer

    def status(self) -> dict[str, Any]:
        """For /status."""
        return {
            "airframe": self.session.id,
            "schedule_id": f"{self.schedule_id:08x}",
            "state": self.state,
            "sends": self.sends,
            "last_result": self.last_result,
            "active_schedule_id": None
            if self.active_schedule_id is None
            else f"{self.active_schedule_id:08x}",
        }


@dataclass(slots=True)
class _Bucket:
    tokens: float = PUBLISH_BURST
    at_mono: float = 0.0

    def take(self, now_mono: float) -> bool:
        self.tokens = min(PUBLISH_BURST, self.tokens + (now_mono - self.at_mono) * PUBLISH_RATE_HZ)
        self.at_mono = now_mono
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


class HopSchedules:
    """Every airframe's hop-schedule upload and hop-event intake; see the module docstring."""

    def __init__(
        self,
        sessions: Iterable[AirframeSession],
        publish: Callable[[Event], bool],
        instruments: Instruments,
        clock: Clock,
    ) -> None:
        self._publish = publish
        self._inst = instruments
        self._clock = clock
        self.uploads: dict[str, HopUpload] = {}
        self._buckets: dict[tuple[str, int], _Bucket] = {}
        self._counted: dict[str, OrderedDict[int, int]] = {}
        self._log = RateLimit(_LOG_INTERVAL_S)
        for session in sessions:
            session.on("FISCHER_HOP_EVENT", self._on_event)
            session.on("FISCHER_HOP_SCHEDULE_ACK", self._on_ack)
            plan = session.config.hop_plan
            if plan is not None:
                self.uploads[session.id] = HopUpload(session, plan, schedule_id(plan))
        instruments.hop_schedule_state.set_function(self._state_series)

    def _state_series(self) -> list[tuple[tuple[str, ...], float]]:
        return [
            ((upload.session.id, state), float(upload.state == state))
            for upload in self.uploads.values()
            for state in STATES
        ]

    def status(self) -> list[dict[str, Any]]:
        """Per airframe with a plan: the upload's state, for /status."""
        return [upload.status() for upload in self.uploads.values()]

    async def run(self) -> None:
        """Upload every airframe's plan, and again whenever it is lost; until cancelled."""
        async with anyio.create_task_group() as tg:
            for upload in self.uploads.values():
                tg.start_soon(self._upload, upload)

    # -- uplink ------------------------------------------------------------------------------

    async def _upload(self, upload: HopUpload) -> None:
        attempt = 0
        while True:
            if upload.state in ("refused", "invalid"):
                await upload.wake.wait()
                upload.wake = anyio.Event()
                continue
            if upload.state == "accepted":
                with anyio.move_on_after(LINK_POLL_S):
                    await upload.wake.wait()
                upload.wake = anyio.Event()
                attempt = 0
                self._watch_reconnect(upload)
                continue
            if upload.session.health.active is None:
                upload.state = "waiting_link"
                with anyio.move_on_after(LINK_POLL_S):
                    await upload.wake.wait()
                upload.wake = anyio.Event()
                continue
            pause_s = upload.resend_at_mono - time.monotonic()
            if pause_s > 0:
                await anyio.sleep(min(pause_s, LINK_POLL_S))
                continue
            frame = self._checked_frame(upload)
            if frame is None:
                continue
            upload.answered = anyio.Event()
            upload.answer = None
            upload.is_awaiting = True
            try:
                await upload.session.send(frame)
            except (LinkError, FrameError):
                pass  # counted by the transmit path; waited out like a lost answer
            else:
                upload.sends += 1
                self._inst.hop_schedule_sends.labels(upload.session.id).inc()
                if upload.state != "retrying":
                    upload.state = "sent"
            wait_s = min(upload.config.ack_timeout_s * 2.0**attempt, upload.config.retry_max_s)
            with anyio.move_on_after(wait_s):
                await upload.answered.wait()
            answer = upload.answer_received()
            if answer is None:
                attempt = min(attempt + 1, 32)
                continue
            attempt = 0
            if answer in _TRANSIENT_RESULTS:
                upload.state = "retrying"
                await anyio.sleep(upload.config.retry_max_s)

    def _watch_reconnect(self, upload: HopUpload) -> None:
        """After every link of an accepted airframe was down, send the plan again: the
        airframe may have rebooted without it (and one without a schedule reports no hops)."""
        if upload.state != "accepted":
            return
        if upload.session.health.active is None:
            upload.link_lost = True
        elif upload.link_lost:
            upload.link_lost = False
            upload.lost()
            if self._log.allow(("reverified", upload.session.id)):
                log.info(
                    "hop_schedule_reverified", airframe=upload.session.id, reason="reconnected"
                )

    def _checked_frame(self, upload: HopUpload) -> bytes | None:
        """The upload's frame, or None (state ``invalid``) if the plan fails its checks."""
        config = upload.config
        try:
            plan = config.plan()
            if not plan.beats_reactive_jammer(config.jammer_reaction_s):
                raise HopPlanError(
                    f"a dwell of {config.dwell_us:g} µs does not beat a jammer reacting in "
                    f"{config.jammer_reaction_us:g} µs"
                )
        except HopPlanError as exc:
            upload.state = "invalid"
            log.error("hop_schedule_invalid", airframe=upload.session.id, reason=str(exc))
            return None
        message = hop_schedule_message(config, upload.session.config.sysid, upload.schedule_id)
        return upload.session.encode(message)

    def _on_ack(self, session: AirframeSession, _label: str, msg: MavMessage) -> None:
        upload = self.uploads.get(session.id)
        if (
            upload is None
            or int(msg.target_system) not in (0, GATEWAY_SYSID)
            or int(msg.target_component) not in (0, GATEWAY_COMPID)
            or int(msg.schedule_id) != upload.schedule_id
        ):
            return  # for someone else, or for a schedule that is not ours
        result = int(msg.result)
        name = HOP_RESULT_NAMES.get(result, "unknown")  # one label for every future value
        self._inst.hop_schedule_answers.labels(session.id, name).inc()
        if not upload.is_awaiting:
            return  # nothing sent, or a second answer (a re-send crossed the first answer)
        upload.is_awaiting = False
        upload.active_schedule_id = int(msg.active_schedule_id)
        upload.last_result = name
        upload.answer = result
        upload.answered.set()
        if result == HOP_RESULT_ACCEPTED:
            if upload.state != "accepted" and self._log.allow(("accepted", session.id)):
                log.info("hop_schedule_accepted", airframe=session.id, sends=upload.sends)
            upload.state = "accepted"
            upload.accepted_mono = time.monotonic()
            upload.link_lost = False
        elif result not in _TRANSIENT_RESULTS:
            upload.state = "refused"
            log.warning("hop_schedule_refused", airframe=session.id, result=name)

    # -- downlink ----------------------------------------------------------------------------

    def _on_event(self, session: AirframeSession, label: str, msg: MavMessage) -> None:
        reason_code = int(msg.reason)
        frequency_hz = int(msg.frequency)
        low, high = AD9361_RANGE_HZ
        if (
            reason_code not in HOP_REASON_NAMES
            or not low <= frequency_hz <= high
            or not 0 <= int(msg.slot) < FASTLOCK_SLOTS
        ):
            self._inst.link_rejected.labels(label, "malformed").inc()
            if self._log.allow(("malformed", session.id)):
                log.warning(
                    "frame_rejected",
                    link=label,
                    reason="malformed",
                    detail="FISCHER_HOP_EVENT with impossible values",
                )
            return
        reason = HOP_REASON_NAMES[reason_code]
        airframe = session.id
        sid, hop_count = int(msg.schedule_id), int(msg.hop_count)
        self._inst.hop_events.labels(airframe, reason).inc()
        self._count_hops(airframe, sid, hop_count)
        upload = self.uploads.get(airframe)
        if upload is not None:
            self._check_active(upload, sid)
        bucket = self._buckets.get((airframe, reason_code))
        if bucket is None:
            bucket = self._buckets[(airframe, reason_code)] = _Bucket(at_mono=time.monotonic())
        if not bucket.take(time.monotonic()):
            self._inst.hop_events_dropped.labels(airframe).inc()
            return
        now = self._clock()
        self._publish(
            HopEvent(
                event_id=event_id(airframe, "hop", f"{sid:08x}", hop_count, int(msg.time_usec)),
                airframe=airframe,
                time=_observed(int(msg.time_usec), now),
                schedule_id=sid,
                is_gateway_schedule=upload is not None
                and upload.state == "accepted"
                and sid == upload.schedule_id,
                slot=int(msg.slot),
                frequency_hz=float(frequency_hz),
                reason=HopReason(reason),
                hop_count=hop_count,
                rssi_dbm=_power(int(msg.rssi)),
                interference_dbm=_power(int(msg.interference)),
            )
        )

    def _count_hops(self, airframe: str, sid: int, hop_count: int) -> None:
        # Per airframe, the last count of its few latest schedules: reports of an old and a
        # new schedule arriving mixed add only what each counter moved on, never it all again.
        counts = self._counted.get(airframe)
        if counts is None:
            counts = self._counted[airframe] = OrderedDict()
        last = counts.get(sid)
        if last is None:
            # A schedule seen for the first time: its count is the hops flown on it so far.
            counts[sid] = hop_count
            if len(counts) > _SCHEDULES_COUNTED:
                counts.popitem(last=False)
            self._inst.hops.labels(airframe).inc(hop_count)
            return
        counts.move_to_end(sid)
        ahead = (hop_count - last) % _U32
        if ahead < _U32 // 2:  # otherwise an older report arriving late: nothing new
            counts[sid] = hop_count
            self._inst.hops.labels(airframe).inc(ahead)

    def _check_active(self, upload: HopUpload, sid: int) -> None:
        upload.active_schedule_id = sid
        if upload.state != "accepted" or sid == upload.schedule_id:
            return
        # Reports sent before the airframe took the schedule may still be on their way.
        grace_s = upload.config.ack_timeout_s
        if upload.accepted_mono is not None and time.monotonic() - upload.accepted_mono < grace_s:
            return
        upload.lost()
        upload.wake.set()
        if self._log.allow(("lost", upload.session.id)):
            log.warning(
                "hop_schedule_lost",
                airframe=upload.session.id,
                schedule_id=f"{upload.schedule_id:08x}",
                reported=f"{sid:08x}",
            )


def _power(dbm: int) -> float | None:
    return None if dbm == POWER_UNKNOWN_DBM else float(dbm)


def _observed(time_usec: int, now: datetime) -> datetime:
    """The airframe's time when it is at most a day behind ours or a minute ahead, else now."""
    ahead_us = time_usec - int(now.timestamp() * 1_000_000)
    if -86_400_000_000 <= ahead_us <= 60_000_000:
        return now + timedelta(microseconds=ahead_us)
    return now
