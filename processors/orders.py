"""The orders processor: five-line orders checked, sent to the airframe, and answered.

``OrdersProcessor`` consumes ``order``, ``telemetry`` and ``track`` events and publishes an
``OrderStatus`` for each state an order reaches: ``waiting`` (its airframe is not heard
yet), ``accepted`` or ``rejected`` (with the check that failed and its numbers), then
``executing``, then ``completed`` or ``failed``; ``conflict`` for an order event seen before
with other content. The source that took the order in reports each to its issuer
(``gateway.c2.source.OrderStatusListener``).

Before anything is sent, the order must pass, in this order: the airframe is configured
(``airframe``), linked and reporting a position (``link``), the time window is not over
(``window``), and the checks of ``processors._orderplan`` (``area``, ``geofence``,
``terrain``, ``endurance``). A rejected order sends nothing to the airframe. An order
refused only by ``link`` waits, within its window (``not_after``, else ``link_wait_s``),
and is checked again as its airframe is heard; at the window's end it is rejected naming
the check that still failed.

An accepted order is carried out through the airframe commander the assembly attaches
(``gateway.flow.tasking``): observe point and track target upload a waypoint and a timed
loiter at the point; area reconnaissance uploads a lawnmower sized by the sensor's
footprint (``processors._coverage``); then the mission is started. Return to base is one
command. The processor asks for these as intents (``upload_mission``, ``start_mission``,
``return_to_base``) and passes its ``mode_commands`` option on with them. Completion is the
airframe's MISSION_ITEM_REACHED of the last item *and* its position there, with time on
task at a final loiter (``processors._orderdone``); MISSION_CURRENT does not count. A
return to base completes when the airframe reports itself disarmed, or has held within
``loiter_radius_m + acceptance_radius_m`` of home for ``home_hold_s`` (a fixed wing on RTL
circles home armed).
One order per airframe at a time: a newer accepted order supersedes the running one, which
is reported ``failed`` saying so. A ``track_target`` order naming the ``track_id`` of a live
fused track flies to that track's newest position and follows it: the orbit is planned,
checked and uploaded again as the track moves (at most once every ``track_replan_s``), and
the order completes when the track is lost or its window ends. Reconnaissance only: nothing
here arms or releases.

Order state is durable when the assembly hands over an order book
(``gateway.domain.orderbook``, the spool's): each order's record (the order, its digest,
where it stands, its mission items, the last item reached, its status sequence) is written
before each status is published, and every status carries its ``seq`` (1, 2, ... per
order). After a restart the statuses kept for unfinished orders (and those finished within
``status_replay_s``) are published again (the issuer drops those it has by ``seq``); a
waiting order waits on until its deadline; an order that was being uploaded is uploaded
again once its airframe is heard; an executing order has the airframe's mission read back
and goes on only if it is still the one uploaded, else it is reported ``failed`` saying so.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import ClassVar, Literal

import anyio
import anyio.abc
import structlog
from anyio.streams.memory import MemoryObjectReceiveStream
from pydantic import BaseModel, ConfigDict, Field, field_validator

from gateway.clock import Clock, utc_now
from gateway.domain.geodesy import distance_bearing
from gateway.domain.mission import Loiter, MissionStep, ModeCommands, polygon_problem
from gateway.domain.orderbook import OrderBook, OrderRecord, Phase
from gateway.domain.terrain import TerrainModel
from gateway.errors import SpoolError
from gateway.events import (
    Event,
    EventKind,
    FiveLineOrder,
    OrderArea,
    OrderState,
    OrderStatus,
    OrderTask,
    Position,
    Telemetry,
    Track,
)
from gateway.flow.processor import ProcessorConfig, Publish
from gateway.flow.tasking import AirframeCommander
from gateway.ops.logsetup import RateLimit
from processors._orderdone import Progress
from processors._orderplan import Limits, Plan, Refusal, check, plan

__all__ = ["OrdersConfig", "OrdersProcessor"]

log = structlog.get_logger(__name__)

_REMEMBERED_ORDERS = 10_000
_REMEMBERED_TRACKS = 10_000
#: How often waiting orders' windows and running orders' time on task are looked at.
_WAIT_TICK_S = 1.0


class Corner(BaseModel):
    """One corner of a geofence, WGS 84 degrees."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    lat_deg: float = Field(ge=-90, le=90, description="Latitude, degrees WGS 84.")
    lon_deg: float = Field(ge=-180, le=180, description="Longitude, degrees WGS 84.")


Fence = tuple[Corner, ...]


class OrdersConfig(ProcessorConfig):
    """Options of the ``orders`` processor (``processors: - {type: orders, options: ...}``)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    geofence: Fence | None = Field(
        default=None,
        min_length=3,
        max_length=256,
        description="The fence every route must stay in (corners in order); none: no fence.",
    )
    airframe_geofences: dict[str, Fence] = Field(
        default_factory=dict, description="Per airframe id, a fence instead of the global one."
    )
    cruise_speed_mps: float = Field(default=25.0, gt=0, le=200, description="For endurance.")
    reserve_min: float = Field(
        default=10.0, ge=0, le=600, description="Endurance left over at the end of the route."
    )
    time_on_task_s: float = Field(
        default=600.0, gt=0, le=86400, description="Loiter time at a point (observe, track)."
    )
    loiter_radius_m: float = Field(default=300.0, gt=0, le=10_000, description="Loiter radius.")
    clearance_m: float = Field(
        default=0.0, ge=0, le=5000, description="Height above ground wanted beyond the 3σ floor."
    )
    mode_commands: ModeCommands = Field(
        default="px4",
        description="How the fleet starts a mission and returns home: px4, PX4's AUTO "
        "MISSION / AUTO RTL modes; mavlink, MISSION_START and NAV_RETURN_TO_LAUNCH.",
    )
    command_timeout_s: float = Field(default=1.5, gt=0, le=60, description="Per COMMAND_ACK.")
    command_retries: int = Field(default=2, ge=0, le=10, description="Resends of a command.")
    mission_timeout_s: float = Field(
        default=2.0, gt=0, le=60, description="Per step of a mission upload."
    )
    mission_retries: int = Field(default=2, ge=0, le=10, description="Restarts of an upload.")
    max_active: int = Field(
        default=64, ge=1, le=10_000, description="Orders being carried out at once, at most."
    )

    link_wait_s: float = Field(
        default=900.0,
        gt=0,
        le=7 * 86400,
        description="How long an order without a not_after waits for its airframe's link.",
    )
    max_waiting: int = Field(
        default=1000, ge=1, le=100_000, description="Orders waiting for a link at once, at most."
    )
    home_hold_s: float = Field(
        default=60.0,
        gt=0,
        le=86400,
        description="How long an airframe that returned home but does not disarm (a fixed "
        "wing circles home) must stay within loiter_radius_m + acceptance_radius_m of home "
        "for return_to_base to complete.",
    )
    acceptance_radius_m: float = Field(
        default=50.0,
        gt=0,
        le=5000,
        description="How near the last item (beyond a loiter's radius) counts as there.",
    )
    camera_hfov_deg: float = Field(
        default=60.0, gt=0, lt=170, description="The sensor's cross-track field of view (survey)."
    )
    survey_overlap: float = Field(
        default=0.2, ge=0, le=0.9, description="Overlap of neighbouring survey swaths (0-0.9)."
    )
    max_survey_lines: int = Field(
        default=100, ge=1, le=1000, description="Most lines a survey may fly."
    )
    track_replan_s: float = Field(
        default=30.0,
        gt=0,
        le=3600,
        description="A followed track's orbit moves at most this often.",
    )
    track_replan_m: float = Field(
        default=100.0, ge=0, le=100_000, description="How far a track moves before the orbit does."
    )

    status_replay_s: float = Field(
        default=3600.0,
        ge=0,
        le=30 * 86400,
        description="After a restart, the statuses of orders finished this recently are sent"
        " again (those of unfinished orders always are).",
    )

    max_start_delay_s: float = Field(
        default=3600.0,
        gt=0,
        le=7 * 86400,
        description="Latest start (not_before) accepted, seconds from now: the checks hold now.",
    )

    @field_validator("geofence")
    @classmethod
    def _simple_fence(cls, fence: Fence | None) -> Fence | None:
        if fence is not None:
            _check_fence(fence, "the fence")
        return fence

    @field_validator("airframe_geofences")
    @classmethod
    def _simple_fences(cls, fences: dict[str, Fence]) -> dict[str, Fence]:
        for airframe, fence in fences.items():
            if len(fence) < 3:
                raise ValueError(f"{airframe}: a fence needs 3+ corners")
            _check_fence(fence, f"{airframe}: the fence")
        return fences


def _check_fence(fence: Fence, what: str) -> None:
    problem = polygon_problem([(c.lat_deg, c.lon_deg) for c in fence])
    if problem is not None:
        raise ValueError(f"{what} {problem}")


@dataclass(slots=True)
class _Waiting:
    """An order waiting for its airframe's link, until ``deadline``."""

    order: FiveLineOrder
    deadline: datetime
    since_s: float
    refusal: Refusal


@dataclass(slots=True)
class _Kept:
    """What the order book keeps of one order (``gateway.domain.orderbook.OrderRecord``)."""

    order: FiveLineOrder
    digest: str
    phase: Phase = "done"
    airframe: str | None = None
    items: tuple[MissionStep, ...] = ()
    deadline: datetime | None = None
    reached: int = -1
    seq: int = 0

    def record(self) -> OrderRecord:
        return OrderRecord(
            order=self.order,
            digest=self.digest,
            phase=self.phase,
            airframe=self.airframe,
            items=self.items,
            deadline=self.deadline,
            reached=self.reached,
            seq=self.seq,
        )


@dataclass(slots=True)
class _Running:
    order: FiveLineOrder
    plan: Plan
    progress: Progress | None = None
    scope: anyio.CancelScope = field(default_factory=anyio.CancelScope)
    changed: anyio.Event = field(default_factory=anyio.Event)
    superseded_by: str | None = None
    #: For a track_target order following a fused track: the track's id, its newest
    #: position not flown yet, whether it was lost, and when the orbit last moved.
    track_id: str | None = None
    track_to: Position | None = None
    track_lost: bool = False
    replanned_s: float = 0.0
    #: After a restart: "upload" (start the upload over) or "check" (read the mission back).
    resumed: str | None = None
    reached: int = -1
    #: For a return to base: since when (monotonic s) the airframe has been near home.
    home_since: float | None = None

    @property
    def items(self) -> int:
        return len(self.plan.items)


class OrdersProcessor:
    """See the module docstring."""

    config_model: ClassVar[type[OrdersConfig]] = OrdersConfig
    kinds: frozenset[EventKind] = frozenset({EventKind.ORDER, EventKind.TELEMETRY, EventKind.TRACK})

    def __init__(
        self,
        name: str,
        config: OrdersConfig,
        *,
        clock: Clock = utc_now,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.name = name
        self.config = config
        self._clock = clock
        self._monotonic = monotonic
        self._commander: AirframeCommander | None = None
        self._terrain: TerrainModel | None = None
        self._baro_sigma_m = 0.5
        self._telemetry: dict[str, Telemetry] = {}
        #: Order event id → its content's digest (a changed order is a conflict), where it
        #: stands and its status sequence, as the order book keeps them.
        self._seen: OrderedDict[str, _Kept] = OrderedDict()
        self._book: OrderBook | None = None
        #: After a restart: airframe → the order to carry on once the airframe is heard.
        self._resuming: dict[str, _Running] = {}
        #: The newest position of each live fused track, for track_target orders naming one.
        self._tracks: OrderedDict[str, Position] = OrderedDict()
        #: Merged track id → the track it was folded into (an order may name either).
        self._merged: OrderedDict[str, str] = OrderedDict()
        self._running: dict[str, _Running] = {}
        self._waiting: OrderedDict[str, _Waiting] = OrderedDict()
        self._tg: anyio.abc.TaskGroup | None = None
        self._publish: Publish = lambda _event: True
        self.counts: dict[str, int] = {}
        self._log_limit = RateLimit(interval_s=5.0)
        self._status_log = RateLimit(interval_s=1.0)
        self.log = log.bind(processor=name)

    def attach(
        self, commander: AirframeCommander, terrain: TerrainModel | None, baro_sigma_m: float
    ) -> None:
        """Take the airframe commander and terrain model (``gateway.app`` does this)."""
        self._commander = commander
        self._terrain = terrain
        self._baro_sigma_m = baro_sigma_m
        commander.on_mission(self._on_mission)

    def keep_orders(self, book: OrderBook) -> None:
        """Keep order state in ``book`` (``gateway.app`` hands over the spool's)."""
        self._book = book

    def status(self) -> dict[str, object]:
        """Counts by status, the orders running and those waiting for a link, for /status."""
        return {
            "counts": dict(self.counts),
            "running": {a: r.order.order_id for a, r in self._running.items()},
            "waiting": [w.order.order_id for w in self._waiting.values()],
            "resuming": {a: r.order.order_id for a, r in self._resuming.items()},
        }

    async def run(
        self,
        events: MemoryObjectReceiveStream[Event],
        publish: Publish,
        *,
        task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Answer orders until the stream ends; each accepted order runs in its own task."""
        self._publish = publish
        async with anyio.create_task_group() as tg:
            self._tg = tg
            self._resume()
            tg.start_soon(self._expire_waiting)
            task_status.started()
            async for event in events:
                if isinstance(event, Telemetry):
                    self._on_telemetry(event)
                elif isinstance(event, Track):
                    self._on_track(event)
                elif isinstance(event, FiveLineOrder):
                    self._on_order(event, tg)
            tg.cancel_scope.cancel()

    # -- status -----------------------------------------------------------------------------

    def _report(
        self,
        order: FiveLineOrder,
        status: OrderState,
        airframe: str | None,
        *,
        check: str | None = None,
        reason: str | None = None,
        items: int | None = None,
        current: int | None = None,
        suffix: str = "",
        phase: Phase | None = None,
    ) -> None:
        self.counts[status.value] = self.counts.get(status.value, 0) + 1
        kept = self._kept(order)
        kept.seq += 1
        if phase is not None:
            kept.phase = phase
        if airframe is not None and status is not OrderState.CONFLICT:
            kept.airframe = airframe
        event = OrderStatus(
            event_id=f"{order.event_id}-{status.value}{suffix}",
            order_event_id=order.event_id,
            order_id=order.order_id,
            source=order.source,
            airframe=airframe,
            time=self._clock(),
            status=status,
            check=check,
            reason=None if reason is None else reason[:512],
            mission_items=items,
            current_item=current,
            seq=kept.seq,
        )
        self._save(kept, event)
        if not self._publish(event) and self._log_limit.allow("refused"):
            self.log.error("order_status_not_held", order_id=order.order_id, status=status.value)
        if not self._status_log.allow(status.value):
            return  # a flood of orders: one line a second per status; all are counted
        self.log.info(
            "order_status",
            order_id=order.order_id,
            source=order.source,
            airframe=airframe,
            status=status.value,
            check=check,
            reason=reason,
        )

    # -- the order book -------------------------------------------------------------------

    def _kept(self, order: FiveLineOrder) -> _Kept:
        kept = self._seen.get(order.event_id)
        if kept is None:  # an order remembered no more (beyond _REMEMBERED_ORDERS)
            kept = self._seen[order.event_id] = _Kept(order, order.content_digest())
        return kept

    def _save(self, kept: _Kept, status: OrderStatus | None = None) -> None:
        """Write the order's record (and the status about to be published) to the book."""
        if self._book is None:
            return
        try:
            self._book.save(kept.record(), status)
        except SpoolError as exc:
            self.counts["book_failed"] = self.counts.get("book_failed", 0) + 1
            if self._log_limit.allow("book_failed"):
                self.log.error("order_book_write_failed", error=str(exc))

    def _resume(self) -> None:
        """Carry on the orders the book kept from before a restart (module docstring)."""
        book = self._book
        if book is None:
            return
        now = self._clock()
        replay_after = now.timestamp() - self.config.status_replay_s
        for record in book.load():
            order = record.order
            kept = _Kept(
                order,
                record.digest,
                record.phase,
                record.airframe,
                record.items,
                record.deadline,
                record.reached,
                record.seq,
            )
            self._seen[order.event_id] = kept
            self._seen.move_to_end(order.event_id)
            if record.phase != "done" or record.updated >= replay_after:
                for status in book.statuses(order.event_id):
                    self.counts["replayed"] = self.counts.get("replayed", 0) + 1
                    self._publish(status)
            if record.phase == "waiting":
                deadline = record.deadline or now
                refusal = Refusal("link", "the node restarted: its airframe is not heard yet")
                self._waiting[order.event_id] = _Waiting(
                    order, deadline, self._monotonic(), refusal
                )
            elif record.phase in ("uploading", "executing") and record.airframe is not None:
                running = _Running(order, _resumed_plan(record.items))
                running.resumed = "upload" if record.phase == "uploading" else "check"
                running.reached = record.reached
                self._resuming[record.airframe] = running
        while len(self._seen) > _REMEMBERED_ORDERS:
            self._seen.popitem(last=False)
        if self._resuming or self._waiting:
            self.log.info(
                "orders_resumed",
                resuming={a: r.order.order_id for a, r in self._resuming.items()},
                waiting=[w.order.order_id for w in self._waiting.values()],
            )

    def _start_resumed(self, airframe: str) -> None:
        """The airframe of an order kept from before a restart is heard: carry it on."""
        tg = self._tg
        commander = self._commander
        if tg is None or commander is None or not commander.is_linked(airframe):
            return
        if airframe in self._running:
            return
        running = self._resuming.pop(airframe)
        self._running[airframe] = running
        tg.start_soon(self._carry_out, airframe, running)

    # -- intake -----------------------------------------------------------------------------

    def _on_order(self, order: FiveLineOrder, tg: anyio.abc.TaskGroup) -> None:
        digest = order.content_digest()
        seen = self._seen.get(order.event_id)
        if seen is None:
            self._seen[order.event_id] = _Kept(order, digest)
            while len(self._seen) > _REMEMBERED_ORDERS:
                self._seen.popitem(last=False)
            self._take(order, tg)
        elif seen.digest != digest:
            # The same order id with other content: answered, never taken (the first stands).
            self._report(
                order,
                OrderState.CONFLICT,
                order.airframe,
                check="order_id",
                reason=f"order {order.order_id} was already taken with other content; the"
                " first stands: give a changed order a new id",
                suffix=f"-{digest[:12]}",
            )

    def _take(self, order: FiveLineOrder, tg: anyio.abc.TaskGroup) -> None:
        airframe, chosen = self._decide(order)
        if isinstance(chosen, Refusal):
            if self._may_wait(order, chosen):
                return
            reason = chosen.reason
            if chosen.check == "link":  # not held: the waiting list is full
                reason += (
                    f"; not held to wait for it: {self.config.max_waiting} orders already"
                    " wait for a link (max_waiting)"
                )
            self._report(
                order,
                OrderState.REJECTED,
                airframe,
                check=chosen.check,
                reason=reason,
                phase="done",
            )
            return
        if airframe is None:  # a plan always names its airframe
            return
        if len(self._running) >= self.config.max_active and airframe not in self._running:
            self._report(
                order,
                OrderState.REJECTED,
                airframe,
                check="capacity",
                reason=f"{self.config.max_active} orders are already being carried out",
                phase="done",
            )
            return
        kept_over = self._resuming.pop(airframe, None)
        if kept_over is not None:  # kept from before a restart, not carried on yet
            self._report(
                kept_over.order,
                OrderState.FAILED,
                airframe,
                check="superseded",
                reason=f"superseded by order {order.order_id}",
                phase="done",
            )
        previous = self._running.get(airframe)
        if previous is not None:
            previous.superseded_by = order.order_id
            previous.scope.cancel()
        running = _Running(order, chosen)
        if order.task is OrderTask.TRACK_TARGET and chosen.items:
            running.track_id = self._live_track(order)
            running.replanned_s = self._monotonic()
        self._running[airframe] = running
        self._kept(order).items = chosen.items
        self._report(
            order, OrderState.ACCEPTED, airframe, items=len(chosen.items), phase="uploading"
        )
        tg.start_soon(self._carry_out, airframe, running)

    def _may_wait(self, order: FiveLineOrder, refusal: Refusal) -> bool:
        """Hold an order refused only for want of a link (see docs/orders.md); True if held."""
        if refusal.check != "link" or order.event_id in self._waiting:
            return order.event_id in self._waiting
        if len(self._waiting) >= self.config.max_waiting:
            self.counts["waiting_full"] = self.counts.get("waiting_full", 0) + 1
            return False
        now = self._clock()
        deadline = order.not_after or now + timedelta(seconds=self.config.link_wait_s)
        self._waiting[order.event_id] = _Waiting(order, deadline, self._monotonic(), refusal)
        self._kept(order).deadline = deadline
        self._report(
            order,
            OrderState.WAITING,
            order.airframe,
            check=refusal.check,
            reason=f"{refusal.reason}; waiting for it until {_iso(deadline)}",
            phase="waiting",
        )
        return True

    def _retry_waiting(self, airframe: str) -> None:
        """Check again the orders waiting for ``airframe`` (or for any), which was just heard."""
        tg = self._tg
        if tg is None:
            return
        heard = self._telemetry[airframe]
        # An airframe just heard may not have reported all the checks need yet: its first
        # messages are not the last word on an order that waited for it.
        unready = None
        if heard.position is None:
            unready = Refusal("link", f"{airframe} has reported no position")
        elif heard.endurance_remaining_min is None:
            unready = Refusal("endurance", f"{airframe} reports no battery state")
        for event_id, waiting in list(self._waiting.items()):
            if waiting.order.airframe not in (None, airframe):
                continue
            if unready is not None:
                waiting.refusal = unready
                continue
            got_airframe, chosen = self._decide(waiting.order)
            if isinstance(chosen, Refusal) and chosen.check == "link":
                waiting.refusal = chosen
                continue
            del self._waiting[event_id]
            if isinstance(chosen, Refusal):
                self._report(
                    waiting.order,
                    OrderState.REJECTED,
                    got_airframe,
                    check=chosen.check,
                    reason=chosen.reason,
                    phase="done",
                )
            else:
                self._take(waiting.order, tg)

    async def _expire_waiting(self) -> None:
        """Reject each waiting order at its window's end, naming the check that still failed."""
        while True:
            await anyio.sleep(_WAIT_TICK_S)
            now = self._clock()
            for event_id, waiting in list(self._waiting.items()):
                if waiting.deadline > now:
                    continue
                del self._waiting[event_id]
                waited_s = self._monotonic() - waiting.since_s
                self._report(
                    waiting.order,
                    OrderState.REJECTED,
                    waiting.order.airframe,
                    check=waiting.refusal.check,
                    reason=f"{waiting.refusal.reason}; waited {waited_s:.0f} s, until the"
                    f" window's end at {_iso(waiting.deadline)}",
                    phase="done",
                )
            for airframe, running in list(self._resuming.items()):
                end = running.order.not_after
                if end is None or end > now:
                    continue
                del self._resuming[airframe]
                self._report(
                    running.order,
                    OrderState.FAILED,
                    airframe,
                    check="link",
                    reason=f"the node restarted and {airframe} was not heard again before the"
                    f" window's end at {_iso(end)}",
                    phase="done",
                )

    def _decide(self, order: FiveLineOrder) -> tuple[str | None, Plan | Refusal]:
        commander = self._commander
        if commander is None:
            return order.airframe, Refusal("airframe", "no airframe commander in this node")
        now = self._clock()
        if order.not_after is not None and order.not_after <= now:
            return order.airframe, Refusal(
                "window", f"the window ended at {order.not_after.isoformat()} (now {_iso(now)})"
            )
        if order.not_before is not None:
            delay_s = (order.not_before - now).total_seconds()
            if delay_s > self.config.max_start_delay_s:
                return order.airframe, Refusal(
                    "window",
                    f"the window starts at {order.not_before.isoformat()}, {delay_s:.0f} s from"
                    f" now; at most {self.config.max_start_delay_s:g} s ahead is taken (the"
                    " checks hold for now, not then)",
                )
        if order.airframe is not None:
            candidates = [order.airframe]
        elif not self._telemetry:
            return None, Refusal("link", "the order names no airframe and none is reporting")
        else:
            candidates = sorted(self._telemetry)
        refusals: list[tuple[str | None, Refusal]] = []
        for airframe in candidates:
            got = self._try(order, airframe, commander)
            if isinstance(got, Plan):
                return airframe, got
            refusals.append((airframe or None, got))
        return refusals[0]

    def _limits(self, airframe: str) -> Limits:
        cfg = self.config
        fence = cfg.airframe_geofences.get(airframe, cfg.geofence)
        return Limits(
            cruise_speed_mps=cfg.cruise_speed_mps,
            reserve_min=cfg.reserve_min,
            time_on_task_s=cfg.time_on_task_s,
            loiter_radius_m=cfg.loiter_radius_m,
            clearance_m=cfg.clearance_m,
            baro_sigma_m=self._baro_sigma_m,
            fence=None if fence is None else tuple((c.lat_deg, c.lon_deg) for c in fence),
            camera_hfov_deg=cfg.camera_hfov_deg,
            survey_overlap=cfg.survey_overlap,
            max_survey_lines=cfg.max_survey_lines,
        )

    def _try(
        self, order: FiveLineOrder, airframe: str, commander: AirframeCommander
    ) -> Plan | Refusal:
        if not commander.is_known(airframe):
            return Refusal("airframe", f"{airframe} is not an airframe of this node")
        telemetry = self._telemetry.get(airframe)
        if not commander.is_linked(airframe) or telemetry is None:
            return Refusal("link", f"{airframe} has no active link")
        limits = self._limits(airframe)
        planned = plan(
            self._aimed(order), telemetry, commander.home(airframe), limits, self._terrain
        )
        if isinstance(planned, Refusal):
            return planned
        refusal = check(planned, telemetry, self._terrain, limits)
        return planned if refusal is None else refusal

    # -- execution --------------------------------------------------------------------------

    async def _carry_out(self, airframe: str, running: _Running) -> None:
        order = running.order
        try:
            with running.scope:
                await self._execute(airframe, running)
            if running.superseded_by is not None:
                self._report(
                    order,
                    OrderState.FAILED,
                    airframe,
                    check="superseded",
                    reason=f"superseded by order {running.superseded_by}",
                    phase="done",
                )
        finally:
            if self._running.get(airframe) is running:
                del self._running[airframe]

    async def _fly(self, airframe: str, running: _Running) -> str | None:
        """Upload the plan's mission and start it (or send the airframe home); None, or the
        failure already reported."""
        commander = self._commander
        if commander is None:  # _decide refuses every order without one
            return "no commander"
        cfg = self.config
        order = running.order
        chosen = running.plan
        if chosen.is_return:
            answered = await commander.return_to_base(
                airframe,
                cfg.mode_commands,
                timeout_s=cfg.command_timeout_s,
                retries=cfg.command_retries,
            )
        else:
            uploaded = await commander.upload_mission(
                airframe, chosen.items, timeout_s=cfg.mission_timeout_s, retries=cfg.mission_retries
            )
            if not uploaded.ok:
                reason = f"mission upload: {uploaded.detail}"
                self._report(
                    order, OrderState.FAILED, airframe, check="mission", reason=reason, phase="done"
                )
                return reason
            running.progress = Progress(chosen.items, cfg.acceptance_radius_m)
            answered = await commander.start_mission(
                airframe,
                len(chosen.items),
                cfg.mode_commands,
                timeout_s=cfg.command_timeout_s,
                retries=cfg.command_retries,
            )
        if not answered.ok:
            self._report(
                order,
                OrderState.FAILED,
                airframe,
                check="command",
                reason=answered.detail,
                phase="done",
            )
            return answered.detail
        return None

    async def _execute(self, airframe: str, running: _Running) -> None:
        order = running.order
        if order.not_before is not None:
            wait_s = (order.not_before - self._clock()).total_seconds()
            if wait_s > 0:
                await anyio.sleep(wait_s)
        if running.resumed == "check":
            if not await self._still_ours(airframe, running):
                return
        else:
            if await self._fly(airframe, running) is not None:
                return
            self._report(
                order,
                OrderState.EXECUTING,
                airframe,
                items=running.items or None,
                phase="executing",
            )
        while True:
            ended = self._ended(airframe, running)
            if ended is not None:
                break
            missed = self._window_missed(running)
            if missed is not None:
                self._report(
                    order,
                    OrderState.FAILED,
                    airframe,
                    check="window",
                    reason=missed,
                    items=running.items or None,
                    phase="done",
                )
                return
            if running.track_to is not None and not await self._follow(airframe, running):
                return
            running.changed = anyio.Event()
            with anyio.move_on_after(_WAIT_TICK_S):
                await running.changed.wait()
        self._report(
            order,
            OrderState.COMPLETED,
            airframe,
            reason=ended or None,
            items=running.items or None,
            current=None if running.items == 0 else running.items - 1,
            phase="done",
        )

    async def _still_ours(self, airframe: str, running: _Running) -> bool:
        """After a restart: read the airframe's mission back; True if it is still this
        order's (progress resumes), else the order is reported failed saying why."""
        commander = self._commander
        if commander is None:
            return False
        cfg = self.config
        if running.items:
            got, steps = await commander.download_mission(
                airframe, timeout_s=cfg.mission_timeout_s, retries=cfg.mission_retries
            )
            why = None
            if not got.ok:
                why = f"its mission could not be read back: {got.detail}"
            else:
                why = _differs(running.plan.items, steps)
            if why is not None:
                self._report(
                    running.order,
                    OrderState.FAILED,
                    airframe,
                    check="mission",
                    reason=f"after a restart of the node, {airframe}'s mission is no longer"
                    f" this order's: {why}",
                    phase="done",
                )
                return False
            running.progress = Progress(running.plan.items, cfg.acceptance_radius_m)
            running.progress.reach(running.reached)
        self.counts["resumed"] = self.counts.get("resumed", 0) + 1
        self.log.info("order_resumed", order_id=running.order.order_id, airframe=airframe)
        return True

    def _window_missed(self, running: _Running) -> str | None:
        """Why an order not done by the end of its window failed (None: not ended yet)."""
        end = running.order.not_after
        if end is None or end > self._clock():
            return None
        progress = running.progress
        if running.items == 0:
            missing = (
                "the airframe had neither landed (still armed) nor held near home for"
                f" {self.config.home_hold_s:g} s"
            )
        elif progress is not None:
            missing = progress.why_not(self._monotonic())
        else:
            missing = "the airframe reported no progress"
        return (
            f"the window ended at {_iso(end)} before the order was done: {missing}"
            " (the airframe flies on with the mission it has)"
        )

    def _ended(self, airframe: str, running: _Running) -> str | None:
        """Why the order is done ("" when it needs no saying), or None while it is not."""
        if running.items == 0:
            telemetry = self._telemetry.get(airframe)
            if telemetry is not None and telemetry.is_armed is False:
                return ""
            since = running.home_since
            if since is not None and self._monotonic() - since >= self.config.home_hold_s:
                return (
                    f"home reached: within {self._home_radius_m():.0f} m of it for"
                    f" {self.config.home_hold_s:g} s, still armed"
                )
            return None
        if running.track_id is not None:
            if running.track_lost:
                return f"track {running.track_id} was lost"
            end = running.order.not_after
            if end is not None and end <= self._clock():
                return f"the window ended at {_iso(end)}"
            return None
        progress = running.progress
        return "" if progress is not None and progress.done(self._monotonic()) else None

    async def _follow(self, airframe: str, running: _Running) -> bool:
        """Move a followed track's orbit to its newest position (at most once every
        ``track_replan_s``); False when the order failed (reported)."""
        to = running.track_to
        now_s = self._monotonic()
        if to is None or now_s - running.replanned_s < self.config.track_replan_s:
            return True
        running.track_to = None
        centre = running.plan.items[-1]
        moved_m, _ = distance_bearing(centre.lat_deg, centre.lon_deg, to.lat_deg, to.lon_deg)
        if moved_m < self.config.track_replan_m:
            return True
        commander = self._commander
        telemetry = self._telemetry.get(airframe)
        if commander is None or telemetry is None:
            return True
        point = Position(lat_deg=to.lat_deg, lon_deg=to.lon_deg, alt_msl_m=centre.alt_msl_m)
        moved = running.order.model_copy(update={"location": OrderArea(point=point)})
        limits = self._limits(airframe)
        planned = plan(moved, telemetry, commander.home(airframe), limits, self._terrain)
        if isinstance(planned, Plan):
            refusal = check(planned, telemetry, self._terrain, limits)
            if refusal is None:
                running.plan = planned
                running.replanned_s = now_s
                self.counts["track_replanned"] = self.counts.get("track_replanned", 0) + 1
                # At most once every track_replan_s per order: the operator's trace of it.
                self.log.info(
                    "order_replanned",
                    order_id=running.order.order_id,
                    airframe=airframe,
                    track_id=running.track_id,
                    lat_deg=round(to.lat_deg, 6),
                    lon_deg=round(to.lon_deg, 6),
                    moved_m=round(moved_m, 1),
                )
                kept = self._kept(running.order)
                kept.items, kept.reached = planned.items, -1
                self._save(kept)
                return await self._fly(airframe, running) is None
        else:
            refusal = planned
        self._report(
            running.order,
            OrderState.FAILED,
            airframe,
            check=refusal.check,
            reason=f"the track moved to {to.lat_deg:.5f}, {to.lon_deg:.5f}: {refusal.reason}",
            phase="done",
        )
        return False

    def _live_track(self, order: FiveLineOrder) -> str | None:
        """The live fused track a track_target order names (a merged one's survivor)."""
        track_id = order.track_id
        if track_id is None:
            return None
        for _ in range(8):  # a merged track's survivor, followed a few merges deep at most
            if track_id not in self._merged:
                break
            track_id = self._merged[track_id]
        return track_id if track_id in self._tracks else None

    def _on_track(self, track: Track) -> None:
        self._tracks.pop(track.track_id, None)
        if track.status == "merged" and track.merged_into is not None:
            self._merged[track.track_id] = track.merged_into
            while len(self._merged) > _REMEMBERED_TRACKS:
                self._merged.popitem(last=False)
        if track.status not in ("lost", "merged"):
            self._tracks[track.track_id] = track.position
            while len(self._tracks) > _REMEMBERED_TRACKS:
                self._tracks.popitem(last=False)
        for running in self._running.values():
            if running.track_id != track.track_id:
                continue
            if track.status == "merged" and track.merged_into is not None:
                running.track_id = track.merged_into  # follow the survivor
            elif track.status == "lost":
                running.track_lost = True
            else:
                running.track_to = track.position
            running.changed.set()

    def _aimed(self, order: FiveLineOrder) -> FiveLineOrder:
        """A track_target order naming a live track flies to the track's newest position."""
        if order.task is not OrderTask.TRACK_TARGET:
            return order
        track_id = self._live_track(order)
        where = None if track_id is None else self._tracks.get(track_id)
        if where is None:
            return order
        given = order.location.point.alt_msl_m if order.location.point is not None else None
        point = Position(lat_deg=where.lat_deg, lon_deg=where.lon_deg, alt_msl_m=given)
        return order.model_copy(update={"location": OrderArea(point=point)})

    def _on_telemetry(self, telemetry: Telemetry) -> None:
        if telemetry.origin_node is not None:
            # Another node's airframe (relayed over NATS): never planned with, never tasked,
            # and never mistaken for one of ours that bears the same id.
            return
        self._telemetry[telemetry.airframe] = telemetry
        running = self._running.get(telemetry.airframe)
        if running is not None:
            where = telemetry.position
            if running.progress is not None and where is not None:
                running.progress.position(where.lat_deg, where.lon_deg, self._monotonic())
            if running.items == 0 and where is not None:
                self._near_home(telemetry.airframe, running, where.lat_deg, where.lon_deg)
            running.changed.set()
        if self._waiting:
            self._retry_waiting(telemetry.airframe)
        if telemetry.airframe in self._resuming:
            self._start_resumed(telemetry.airframe)

    def _home_radius_m(self) -> float:
        return self.config.loiter_radius_m + self.config.acceptance_radius_m

    def _near_home(self, airframe: str, running: _Running, lat_deg: float, lon_deg: float) -> None:
        """Follow a returning airframe's time near its home (never while home is unknown)."""
        home = None if self._commander is None else self._commander.home(airframe)
        if home is None:
            running.home_since = None
            return
        distance_m, _ = distance_bearing(lat_deg, lon_deg, home[0], home[1])
        if distance_m > self._home_radius_m():
            running.home_since = None
        elif running.home_since is None:
            running.home_since = self._monotonic()

    def _on_mission(self, airframe: str, what: Literal["current", "reached"], seq: int) -> None:
        running = self._running.get(airframe)
        if running is None or running.progress is None or what != "reached":
            return  # MISSION_CURRENT says what the airframe flies, not what it has done
        # Only items this order uploaded count; anything else is a lie or another mission's.
        before = running.progress.reached
        if not running.progress.reach(seq):
            self.counts["progress_ignored"] = self.counts.get("progress_ignored", 0) + 1
            return
        if running.progress.reached != before:
            kept = self._kept(running.order)
            kept.reached = running.progress.reached
            self._save(kept)
        running.changed.set()


def _resumed_plan(items: tuple[MissionStep, ...]) -> Plan:
    """The plan of an order carried on after a restart: its mission items (the checks held
    when it was accepted)."""
    alt = items[-1].alt_msl_m if items else 0.0
    return Plan(items=items, task_points=(), route=(), alt_msl_m=alt, on_task_s=0.0, route_m=0.0)


#: How near a read-back item must be to the uploaded one: MAVLink carries 1e-7° and float32.
_SAME_DEG = 2e-7
_SAME_M = 0.05


def _differs(planned: tuple[MissionStep, ...], got: tuple[MissionStep, ...]) -> str | None:
    """Why the airframe's mission ``got`` is not ``planned`` (None if it is the same)."""
    if len(got) != len(planned):
        return f"it has {len(got)} items, the order uploaded {len(planned)}"
    for seq, (mine, theirs) in enumerate(zip(planned, got, strict=True)):
        if type(mine) is not type(theirs):
            return f"item {seq} is a {type(theirs).__name__}, not a {type(mine).__name__}"
        if (
            abs(mine.lat_deg - theirs.lat_deg) > _SAME_DEG
            or abs(mine.lon_deg - theirs.lon_deg) > _SAME_DEG
            or abs(mine.alt_msl_m - theirs.alt_msl_m) > _SAME_M
        ):
            return (
                f"item {seq} is at {theirs.lat_deg:.7f}, {theirs.lon_deg:.7f},"
                f" {theirs.alt_msl_m:.1f} m; the order uploaded {mine.lat_deg:.7f},"
                f" {mine.lon_deg:.7f}, {mine.alt_msl_m:.1f} m"
            )
        if (
            isinstance(mine, Loiter)
            and isinstance(theirs, Loiter)
            and (
                abs(mine.seconds - theirs.seconds) > _SAME_M
                or abs(mine.radius_m - theirs.radius_m) > _SAME_M
            )
        ):
            return (
                f"item {seq} loiters {theirs.seconds:.0f} s at {theirs.radius_m:.0f} m; the"
                f" order uploaded {mine.seconds:.0f} s at {mine.radius_m:.0f} m"
            )
    return None


def _iso(moment: datetime) -> str:
    return moment.isoformat()
