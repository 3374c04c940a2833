"""Processor ``orders``: the acceptance checks, the translation, and the statuses it reports.

The airframe side is an in-memory ``AirframeCommander`` that records every call: a unit test
of the processor's decisions. The same processor against MAVSDK through ``fischer-gateway
run`` is tests/e2e/test_orders_run.py.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any, Literal

import anyio
import numpy as np
import pytest
import structlog.testing

from gateway.domain.mission import (
    Loiter,
    MissionStep,
    ModeCommands,
    Outcome,
    Waypoint,
    route_length_m,
)
from gateway.domain.terrain import DemSource, TerrainModel
from gateway.events import (
    Event,
    FiveLineOrder,
    OrderArea,
    OrderState,
    OrderStatus,
    OrderTask,
    Position,
    Telemetry,
    Track,
    event_adapter,
)
from gateway.flow.tasking import AirframeCommander, MissionListener, TaskingProcessor
from processors._orderplan import Limits, Plan, Refusal, check, plan
from processors.orders import OrdersConfig, OrdersProcessor

NOW = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)
HERE = (65.83, 21.00)
FENCE = [
    {"lat_deg": 65.0, "lon_deg": 20.0},
    {"lat_deg": 65.0, "lon_deg": 24.0},
    {"lat_deg": 67.0, "lon_deg": 24.0},
    {"lat_deg": 67.0, "lon_deg": 20.0},
]


class Commander:
    """Records what the processor asks of the airframe side; answers as told."""

    def __init__(self, *, linked: bool = True, upload_ok: bool = True, ack: bool = True) -> None:
        self.linked = linked
        self.upload_ok = upload_ok
        self.ack = ack
        self.uploads: list[tuple[str, list[MissionStep]]] = []
        self.commands: list[tuple[str, str, int | None, ModeCommands]] = []
        self.listeners: list[MissionListener] = []
        self.mission: tuple[MissionStep, ...] | None = None

    def is_known(self, airframe: str) -> bool:
        return airframe == "F26E-001"

    def is_linked(self, airframe: str) -> bool:
        return self.linked

    def home(self, airframe: str) -> tuple[float, float] | None:
        return HERE

    def _answer(self, retries: int) -> Outcome:
        if self.ack:
            return Outcome(True, "MAV_RESULT_ACCEPTED")
        return Outcome(False, f"no answer after {retries + 1} attempts")

    async def start_mission(
        self,
        airframe: str,
        items: int,
        mode_commands: ModeCommands,
        *,
        timeout_s: float,
        retries: int,
    ) -> Outcome:
        self.commands.append((airframe, "start", items, mode_commands))
        return self._answer(retries)

    async def return_to_base(
        self, airframe: str, mode_commands: ModeCommands, *, timeout_s: float, retries: int
    ) -> Outcome:
        self.commands.append((airframe, "return", None, mode_commands))
        return self._answer(retries)

    async def upload_mission(
        self, airframe: str, steps: Sequence[MissionStep], *, timeout_s: float, retries: int
    ) -> Outcome:
        self.uploads.append((airframe, list(steps)))
        return Outcome(
            self.upload_ok, "MAV_MISSION_ACCEPTED" if self.upload_ok else "MAV_MISSION_DENIED"
        )

    async def download_mission(
        self, airframe: str, *, timeout_s: float, retries: int
    ) -> tuple[Outcome, tuple[MissionStep, ...]]:
        """The mission last uploaded (or ``mission`` when set: another one)."""
        if self.mission is not None:
            return Outcome(True, "read back"), self.mission
        steps = tuple(self.uploads[-1][1]) if self.uploads else ()
        return Outcome(True, "read back"), steps

    def on_mission(self, listener: MissionListener) -> None:
        self.listeners.append(listener)

    def progress(self, what: Literal["current", "reached"], seq: int) -> None:
        for listener in self.listeners:
            listener("F26E-001", what, seq)


def telemetry(
    *,
    battery_pct: float | None = 80.0,
    alt: float = 500.0,
    armed: bool = True,
    at: tuple[float, float] = HERE,
) -> Telemetry:
    endurance = None if battery_pct is None else 60 * 800 * battery_pct / 100 / 415
    return Telemetry(
        event_id="t",
        airframe="F26E-001",
        time=NOW,
        position=Position(lat_deg=at[0], lon_deg=at[1], alt_msl_m=alt),
        alt_agl_m=alt - 100.0,
        battery_pct=battery_pct,
        endurance_remaining_min=endurance,
        is_armed=armed,
    )


def order(
    order_id: str = "O-1",
    *,
    task: OrderTask = OrderTask.OBSERVE_POINT,
    at: tuple[float, float] = (65.85, 21.10),
    polygon: Sequence[tuple[float, float]] = (),
    airframe: str | None = "F26E-001",
    **extra: Any,
) -> FiveLineOrder:
    area = (
        OrderArea(polygon=tuple(Position(lat_deg=a, lon_deg=b) for a, b in polygon))
        if polygon
        else OrderArea(point=Position(lat_deg=at[0], lon_deg=at[1]))
    )
    return FiveLineOrder(
        event_id=f"slb-order-{order_id}",
        order_id=order_id,
        source="brigade-slb",
        time=NOW,
        airframe=airframe,
        task=task,
        location=area,
        **extra,
    )


def track(track_id: str, *, at: tuple[float, float], status: str = "updated") -> Track:
    return Track.model_validate(
        {
            "event_id": f"{track_id}-{at}-{status}",
            "track_id": track_id,
            "time": NOW,
            "status": status,
            "object_class": "tank",
            "confidence": 0.9,
            "position": {"lat_deg": at[0], "lon_deg": at[1]},
            "cep50_m": 10.0,
            "cep90_m": 20.0,
            "first_seen": NOW,
            "last_seen": NOW,
        }
    )


def limits(**changes: Any) -> Limits:
    base: dict[str, Any] = {
        "cruise_speed_mps": 25.0,
        "reserve_min": 10.0,
        "time_on_task_s": 600.0,
        "loiter_radius_m": 300.0,
        "clearance_m": 0.0,
        "baro_sigma_m": 0.5,
        "fence": tuple((c["lat_deg"], c["lon_deg"]) for c in FENCE),
    }
    return Limits(**{**base, **changes})


def hill_terrain(tmp_path: Path, tile: str = "N65E021") -> TerrainModel:
    grid = np.full((1201, 1201), 100, dtype=">i2")
    grid[60:121, 480:541] = 650
    (tmp_path / f"{tile}.hgt").write_bytes(grid.tobytes())
    return TerrainModel([DemSource("srtm", tmp_path, "hgt", 5.0)])


class TestPlan:
    def test_observe_point_is_a_waypoint_then_a_timed_loiter_at_the_current_altitude(self) -> None:
        got = plan(order(), telemetry(), None, limits())
        assert isinstance(got, Plan)
        assert [type(i) for i in got.items] == [Waypoint, Loiter]
        loiter = got.items[1]
        assert isinstance(loiter, Loiter)
        assert (loiter.seconds, loiter.radius_m) == (600.0, 300.0)
        assert {i.alt_msl_m for i in got.items} == {500.0}
        assert got.route == (HERE, (65.85, 21.10), HERE)

    def test_an_area_is_flown_as_a_lawnmower_sized_by_the_footprint(self) -> None:
        corners = [(65.84, 21.02), (65.84, 21.06), (65.86, 21.06)]
        got = plan(order(task=OrderTask.RECON_AREA, polygon=corners), telemetry(), None, limits())
        assert isinstance(got, Plan)
        # 400 m above the ground at 60° cross-track: a 462 m swath, lines ≤ 370 m apart.
        assert got.swath_m == pytest.approx(2 * 400 * math.tan(math.radians(30)))
        assert len(got.items) % 2 == 0
        assert len(got.items) >= 2 * 3  # 1.3 km deep across the longest edge (the hypotenuse)
        assert {i.alt_msl_m for i in got.items} == {500.0}
        assert got.on_task_s * 25.0 == pytest.approx(route_length_m(got.task_points))

    def test_a_survey_without_height_above_ground_is_refused(self) -> None:
        corners = [(65.84, 21.02), (65.84, 21.06), (65.86, 21.06)]
        blind = telemetry().model_copy(update={"alt_agl_m": None})
        got = plan(order(task=OrderTask.RECON_AREA, polygon=corners), blind, None, limits())
        assert isinstance(got, Refusal)
        assert got.check == "area"
        assert got.reason.startswith("no height above ground to size the sensor footprint")
        # Its height above home stands in (the area's ground taken as home's): 300 m up.
        assert blind.position is not None
        homed = blind.model_copy(
            update={"position": blind.position.model_copy(update={"alt_rel_home_m": 300.0})}
        )
        got = plan(order(task=OrderTask.RECON_AREA, polygon=corners), homed, None, limits())
        assert isinstance(got, Plan)
        assert got.swath_m == pytest.approx(2 * 300 * math.tan(math.radians(30)))

    def test_return_to_base_is_no_mission(self) -> None:
        got = plan(order(task=OrderTask.RETURN_TO_BASE), telemetry(), (65.9, 21.2), limits())
        assert isinstance(got, Plan)
        assert got.is_return
        assert got.route == (HERE, (65.9, 21.2))

    def test_the_altitude_the_order_gives_is_commanded(self) -> None:
        area = OrderArea(point=Position(lat_deg=65.85, lon_deg=21.1, alt_msl_m=720.0))
        got = plan(order().model_copy(update={"location": area}), telemetry(), None, limits())
        assert isinstance(got, Plan)
        assert {i.alt_msl_m for i in got.items} == {720.0}


class TestChecks:
    def test_within_everything_passes(self, tmp_path: Path) -> None:
        got = plan(order(), telemetry(), None, limits())
        assert isinstance(got, Plan)
        assert check(got, telemetry(), hill_terrain(tmp_path), limits()) is None

    def test_out_of_endurance_names_the_minutes(self) -> None:
        far = plan(order(at=(66.95, 23.95)), telemetry(), None, limits())
        assert isinstance(far, Plan)
        refusal = check(far, telemetry(), None, limits())
        assert isinstance(refusal, Refusal)
        assert refusal.check == "endurance"
        have = telemetry().endurance_remaining_min
        assert have is not None
        assert refusal.reason.endswith(f"has {have:.1f} min")
        assert "+ reserve 10 min" in refusal.reason

    def test_the_return_leg_counts(self) -> None:
        """Out and back fits only without the way home: the order is refused."""
        near = plan(order(at=(66.3, 21.0)), telemetry(battery_pct=60.0), None, limits())
        assert isinstance(near, Plan)
        one_way_min = 52_400 / 25 / 60  # about 52 km to the point
        have = telemetry(battery_pct=60.0).endurance_remaining_min
        assert have is not None
        assert one_way_min + 10 + 10 < have < 2 * one_way_min + 10 + 10
        refusal = check(near, telemetry(battery_pct=60.0), None, limits())
        assert isinstance(refusal, Refusal)
        assert refusal.check == "endurance"

    def test_no_battery_state_is_refused(self) -> None:
        got = plan(order(), telemetry(battery_pct=None), None, limits())
        assert isinstance(got, Plan)
        refusal = check(got, telemetry(battery_pct=None), None, limits())
        assert refusal == Refusal("endurance", "F26E-001 reports no battery state")

    def test_outside_the_fence_names_the_point(self) -> None:
        got = plan(order(at=(64.5, 21.0)), telemetry(), None, limits())
        assert isinstance(got, Plan)
        refusal = check(got, telemetry(), None, limits())
        assert refusal == Refusal(
            "geofence",
            "the route leaves the geofence at 64.50000, 21.00000 (lat, lon), 56.9 km outside",
        )

    def test_below_the_terrain_floor_names_floor_ground_and_sigma(self, tmp_path: Path) -> None:
        got = plan(order(at=(65.925, 21.425)), telemetry(), None, limits())
        assert isinstance(got, Plan)
        refusal = check(got, telemetry(), hill_terrain(tmp_path), limits())
        assert isinstance(refusal, Refusal)
        assert refusal.check == "terrain"
        assert "ground 650.0 m" in refusal.reason
        sigma = (0.5**2 + 5.0**2) ** 0.5
        assert f"below the floor {650 + 3 * sigma:.1f} m MSL" in refusal.reason
        assert "ground 650.0 m" in refusal.reason

    def test_the_loiter_circle_is_checked_too(self, tmp_path: Path) -> None:
        """A point just beside the hill: the circle round it crosses the high ground."""
        beside = plan(order(at=(65.925, 21.452)), telemetry(), None, limits())
        assert isinstance(beside, Plan)
        refusal = check(beside, telemetry(), hill_terrain(tmp_path), limits())
        assert isinstance(refusal, Refusal)
        assert refusal.check == "terrain"

    def test_where_no_dem_covers_there_is_no_terrain_check(self, tmp_path: Path) -> None:
        got = plan(order(), telemetry(alt=10.0), None, limits())
        assert isinstance(got, Plan)
        elsewhere = hill_terrain(tmp_path, "N64E021")
        assert check(got, telemetry(alt=10.0), elsewhere, limits()) is None
        assert check(got, telemetry(alt=10.0), hill_terrain(tmp_path), limits()) is not None

    def test_the_inbound_leg_is_checked(self, tmp_path: Path) -> None:
        """The point is clear of the hill, the way there crosses it."""
        got = plan(order(at=(66.05, 21.85)), telemetry(), None, limits())
        assert isinstance(got, Plan)
        refusal = check(got, telemetry(), hill_terrain(tmp_path), limits())
        assert isinstance(refusal, Refusal)
        assert refusal.check == "terrain"
        assert "ground 650.0 m" in refusal.reason


async def run_orders(
    commander: Commander,
    events: Sequence[Event],
    *,
    options: dict[str, Any] | None = None,
    after: Any = None,
    after_state: OrderState = OrderState.EXECUTING,
    until: Any = None,
    settle: bool = False,
) -> list[OrderStatus]:
    """Feed ``events``; call ``after(commander)``; wait for ``until(statuses)``; statuses."""
    config = OrdersConfig.model_validate({"geofence": FENCE, **(options or {})})
    started = time.monotonic()
    processor = OrdersProcessor(
        "orders", config, clock=lambda: NOW + timedelta(seconds=time.monotonic() - started)
    )
    assert isinstance(processor, TaskingProcessor)
    assert isinstance(commander, AirframeCommander)
    processor.attach(commander, None, 0.5)
    published: list[OrderStatus] = []
    changed = anyio.Event()

    def publish(event: Event) -> bool:
        nonlocal changed
        assert isinstance(event, OrderStatus)
        published.append(event)
        changed.set()
        changed = anyio.Event()
        return True

    send, receive = anyio.create_memory_object_stream[Event](100)
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            await tg.start(processor.run, receive, publish)
            for event in events:
                await send.send(event)
            if after is not None:
                while not any(s.status is after_state for s in published):
                    await changed.wait()
                for event in after(commander) or ():
                    await send.send(event)
                if settle:  # every task has taken what it was given and is waiting again
                    await anyio.wait_all_tasks_blocked()
                    until = lambda _s: True  # noqa: E731 - stop here
            while not (until or (lambda s: len(s) >= 1))(published):
                with anyio.move_on_after(0.05):  # ``until`` may look at the commander too
                    await changed.wait()
            await send.aclose()
    receive.close()
    return published


def states(published: Sequence[OrderStatus], order_id: str = "O-1") -> list[str]:
    return [s.status.value for s in published if s.order_id == order_id]


@pytest.mark.anyio
class TestProcessor:
    async def test_an_accepted_point_order_runs_to_completed(self) -> None:
        commander = Commander()

        def fly(c: Commander) -> list[Event]:
            c.progress("current", 0)
            c.progress("reached", 0)
            c.progress("current", 1)
            c.progress("reached", 1)
            return [telemetry(at=(65.851, 21.101))]

        published = await run_orders(
            commander,
            [telemetry(), order()],
            options={"time_on_task_s": 0.2},
            after=fly,
            until=lambda s: any(x.status is OrderState.COMPLETED for x in s),
        )
        assert states(published) == ["accepted", "executing", "completed"]
        ((airframe, items),) = commander.uploads
        assert airframe == "F26E-001"
        assert [type(i) for i in items] == [Waypoint, Loiter]
        assert commander.commands == [("F26E-001", "start", 2, "px4")]
        assert published[-1].event_id == "slb-order-O-1-completed"
        assert published[-1].source == "brigade-slb"
        assert published[-1].current_item == 1

    async def test_another_nodes_telemetry_is_never_planned_with(self) -> None:
        """An airframe relayed from another node (``origin_node``) under one of our ids."""
        remote = telemetry().model_copy(update={"origin_node": "brigade-2"})
        published = await run_orders(Commander(), [remote, order()])
        assert states(published) == ["waiting"]
        assert published[0].check == "link"

    async def test_mavlink_mode_commands_are_passed_on_with_the_intent(self) -> None:
        commander = Commander()
        await run_orders(
            commander,
            [telemetry(), order()],
            options={"mode_commands": "mavlink"},
            until=lambda s: any(x.status is OrderState.EXECUTING for x in s),
        )
        assert commander.commands == [("F26E-001", "start", 2, "mavlink")]

    async def test_a_rejected_order_sends_nothing(self) -> None:
        commander = Commander()
        published = await run_orders(commander, [telemetry(), order(at=(64.5, 21.0))])
        assert states(published) == ["rejected"]
        assert published[0].check == "geofence"
        assert commander.uploads == []
        assert commander.commands == []

    async def test_an_unknown_airframe_is_rejected_by_name(self) -> None:
        published = await run_orders(Commander(), [telemetry(), order(airframe="F26E-404")])
        assert (published[0].check, published[0].reason) == (
            "airframe",
            "F26E-404 is not an airframe of this node",
        )

    async def test_an_airframe_without_a_link_waits_then_is_rejected_at_the_windows_end(
        self,
    ) -> None:
        soon = order(not_after=NOW + timedelta(seconds=1))
        published = await run_orders(
            Commander(linked=False), [telemetry(), soon], until=lambda s: len(s) >= 2
        )
        assert states(published) == ["waiting", "rejected"]
        assert published[0].check == "link"
        assert published[0].reason is not None
        assert published[0].reason.startswith("F26E-001 has no active link; waiting for it until")
        assert published[1].check == "link"
        assert published[1].reason is not None
        assert published[1].reason.startswith("F26E-001 has no active link; waited ")
        assert "until the window's end at 2026-11-22T12:00:01+00:00" in published[1].reason

    async def test_an_order_beyond_max_waiting_is_rejected_saying_the_list_is_full(
        self,
    ) -> None:
        published = await run_orders(
            Commander(linked=False),
            [telemetry(), order("O-1"), order("O-2")],
            options={"max_waiting": 1},
            until=lambda s: len(s) >= 2,
        )
        assert [(s.order_id, s.status.value) for s in published] == [
            ("O-1", "waiting"),
            ("O-2", "rejected"),
        ]
        assert published[1].check == "link"
        assert published[1].reason == (
            "F26E-001 has no active link; not held to wait for it: 1 orders already wait for"
            " a link (max_waiting)"
        )

    async def test_an_order_before_the_airframe_is_heard_is_flown_once_it_is(self) -> None:
        commander = Commander(linked=False)

        def heard(c: Commander) -> list[Event]:
            c.linked = True
            return [telemetry()]

        published = await run_orders(
            commander,
            [order()],
            after=heard,
            after_state=OrderState.WAITING,
            until=lambda s: any(x.status is OrderState.EXECUTING for x in s),
        )
        assert states(published) == ["waiting", "accepted", "executing"]
        assert published[0].reason is not None
        assert published[0].reason.startswith("F26E-001 has no active link; waiting for it")
        assert len(commander.uploads) == 1

    async def test_an_order_not_done_by_its_windows_end_fails_saying_what_was_missing(
        self,
    ) -> None:
        commander = Commander()

        def half_way(c: Commander) -> list[Event]:
            c.progress("reached", 0)  # the waypoint, never the loiter
            return [telemetry(at=(65.851, 21.101))]

        published = await run_orders(
            commander,
            [telemetry(), order(not_after=NOW + timedelta(seconds=1))],
            after=half_way,
            until=lambda s: any(x.status is OrderState.FAILED for x in s),
        )
        assert states(published) == ["accepted", "executing", "failed"]
        assert published[-1].check == "window"
        assert published[-1].reason is not None
        assert published[-1].reason.startswith(
            "the window ended at 2026-11-22T12:00:01+00:00 before the order was done:"
            " the airframe reported item 0 of 1 reached"
        )

    async def test_an_order_whose_window_ended_is_rejected(self) -> None:
        late = order(not_after=NOW - timedelta(minutes=1))
        published = await run_orders(Commander(), [telemetry(), late])
        assert published[0].check == "window"

    async def test_an_order_for_any_airframe_waits_for_one_to_report(self) -> None:
        def heard(c: Commander) -> list[Event]:
            return [telemetry(battery_pct=None), telemetry()]  # no battery state yet, then one

        published = await run_orders(
            Commander(),
            [order(airframe=None)],
            after=heard,
            after_state=OrderState.WAITING,
            until=lambda s: any(x.status is OrderState.EXECUTING for x in s),
        )
        assert states(published) == ["waiting", "accepted", "executing"]
        assert published[0].reason is not None
        assert published[0].reason.startswith(
            "the order names no airframe and none is reporting; waiting for it until"
        )
        assert published[1].airframe == "F26E-001"

    async def test_an_order_for_any_airframe_takes_one_that_reports(self) -> None:
        commander = Commander()
        published = await run_orders(
            commander,
            [telemetry(), order(airframe=None)],
            until=lambda s: any(x.status is OrderState.EXECUTING for x in s),
        )
        assert {s.airframe for s in published} == {"F26E-001"}

    async def test_a_refused_mission_fails_the_order_and_starts_nothing(self) -> None:
        commander = Commander(upload_ok=False)
        published = await run_orders(
            commander,
            [telemetry(), order()],
            until=lambda s: any(x.status is OrderState.FAILED for x in s),
        )
        assert states(published) == ["accepted", "failed"]
        assert published[-1].reason == "mission upload: MAV_MISSION_DENIED"
        assert commander.commands == []

    async def test_an_unacknowledged_command_fails_the_order(self) -> None:
        published = await run_orders(
            Commander(ack=False),
            [telemetry(), order()],
            until=lambda s: any(x.status is OrderState.FAILED for x in s),
        )
        assert published[-1].check == "command"
        assert published[-1].reason == "no answer after 3 attempts"

    async def test_a_newer_order_supersedes_the_running_one(self) -> None:
        commander = Commander()
        published = await run_orders(
            commander,
            [telemetry(), order("O-1"), order("O-2", at=(65.86, 21.12))],
            until=lambda s: (
                any(x.status is OrderState.FAILED for x in s)
                and any(x.order_id == "O-2" and x.status is OrderState.EXECUTING for x in s)
            ),
        )
        assert states(published, "O-1")[-1] == "failed"
        assert [s.reason for s in published if s.status is OrderState.FAILED] == [
            "superseded by order O-2"
        ]
        assert len(commander.uploads) == 2

    async def test_return_to_base_completes_once_disarmed(self) -> None:
        commander = Commander()
        rtb = order(task=OrderTask.RETURN_TO_BASE)
        published = await run_orders(
            commander,
            [telemetry(), rtb, telemetry(armed=False)],
            until=lambda s: any(x.status is OrderState.COMPLETED for x in s),
        )
        assert states(published) == ["accepted", "executing", "completed"]
        assert commander.uploads == []
        assert commander.commands == [("F26E-001", "return", None, "px4")]

    async def test_return_to_base_completes_once_held_near_home_armed(self) -> None:
        """A fixed wing on RTL circles home armed: holding near home for home_hold_s is done."""
        published = await run_orders(
            Commander(),
            [telemetry(at=(65.9, 21.3)), order(task=OrderTask.RETURN_TO_BASE)],
            options={"home_hold_s": 0.2},
            after=lambda c: [telemetry(at=(65.8305, 21.0005))],  # ~60 m from home
            until=lambda s: any(x.status is OrderState.COMPLETED for x in s),
        )
        assert states(published) == ["accepted", "executing", "completed"]
        assert published[-1].reason == "home reached: within 350 m of it for 0.2 s, still armed"

    async def test_return_to_base_far_from_home_is_not_done(self) -> None:
        deadline = time.monotonic() + 1.0  # ten times home_hold_s
        published = await run_orders(
            Commander(),
            [telemetry(at=(65.9, 21.3)), order(task=OrderTask.RETURN_TO_BASE)],
            options={"home_hold_s": 0.1},
            after=lambda c: [telemetry(at=(65.9, 21.3))],  # still 16 km out
            until=lambda s: time.monotonic() > deadline,
        )
        assert states(published) == ["accepted", "executing"]

    async def test_the_same_order_twice_is_answered_once(self) -> None:
        published = await run_orders(
            Commander(linked=False),
            [telemetry(), order(), order(), order("O-3")],
            until=lambda s: len(s) >= 2,
        )
        assert [s.order_id for s in published] == ["O-1", "O-3"]

    async def test_the_same_order_id_with_changed_content_is_a_conflict(self) -> None:
        changed = order(at=(65.86, 21.12))
        published = await run_orders(
            Commander(),
            [telemetry(), order(), order(), changed],
            until=lambda s: any(x.status is OrderState.CONFLICT for x in s),
        )
        conflict = published[-1]
        assert [s.status.value for s in published[:1]] == ["accepted"]
        assert (conflict.order_id, conflict.check) == ("O-1", "order_id")
        assert conflict.reason is not None
        assert "already taken with other content" in conflict.reason
        assert conflict.event_id.startswith("slb-order-O-1-conflict-")
        assert sum(s.status is OrderState.CONFLICT for s in published) == 1

    async def test_a_mission_current_past_the_end_is_not_completion(self) -> None:
        """A hostile airframe says it is done; its positions say otherwise."""
        commander = Commander()
        area = order(
            task=OrderTask.RECON_AREA, polygon=[(65.84, 21.02), (65.84, 21.06), (65.86, 21.06)]
        )

        def lie(c: Commander) -> list[Event]:
            ((_, steps),) = c.uploads
            c.progress("current", len(steps))  # one past the last: no longer counts
            c.progress("reached", len(steps) - 1)  # the last, but the airframe is elsewhere
            c.progress("reached", len(steps) + 5)  # an item it was never given
            return [telemetry(), telemetry()]  # still at home

        published = await run_orders(commander, [telemetry(), area], after=lie, settle=True)
        assert states(published) == ["accepted", "executing"]

    async def test_a_survey_completes_at_the_last_item_reached_and_flown_to(self) -> None:
        commander = Commander()
        area = order(
            task=OrderTask.RECON_AREA, polygon=[(65.84, 21.02), (65.84, 21.06), (65.86, 21.06)]
        )

        def fly(c: Commander) -> list[Event]:
            ((_, steps),) = c.uploads
            last = steps[-1]
            c.progress("reached", len(steps) - 1)
            return [telemetry(at=(last.lat_deg, last.lon_deg))]

        published = await run_orders(
            commander,
            [telemetry(), area],
            after=fly,
            until=lambda s: any(x.status is OrderState.COMPLETED for x in s),
        )
        assert states(published) == ["accepted", "executing", "completed"]

    async def test_track_target_follows_the_track_and_completes_when_it_is_lost(self) -> None:
        commander = Commander()
        first = track("T-7", at=(65.85, 21.10))
        moved = track("T-7", at=(65.86, 21.14))
        lost = track("T-7", at=(65.86, 21.14), status="lost")
        follow = order(task=OrderTask.TRACK_TARGET, track_id="T-7")

        def move(c: Commander) -> list[Event]:
            return [moved, telemetry()]

        with structlog.testing.capture_logs() as logs:
            published = await run_orders(
                commander,
                [telemetry(), first, follow],
                options={"track_replan_s": 0.05},
                after=move,
                until=lambda s: len(commander.uploads) >= 2,
            )
        assert states(published) == ["accepted", "executing"]
        second = commander.uploads[1][1][-1]
        assert (second.lat_deg, second.lon_deg) == (65.86, 21.14)
        (replanned,) = [line for line in logs if line["event"] == "order_replanned"]
        assert (replanned["track_id"], replanned["lat_deg"]) == ("T-7", 65.86)
        published = await run_orders(
            Commander(),
            [telemetry(), first, follow, lost],
            until=lambda s: any(x.status is OrderState.COMPLETED for x in s),
        )
        assert states(published) == ["accepted", "executing", "completed"]
        assert published[-1].reason == "track T-7 was lost"


@pytest.mark.anyio
async def test_a_followed_track_that_leaves_the_fence_fails_the_order() -> None:
    commander = Commander()
    follow = order(task=OrderTask.TRACK_TARGET, track_id="T-8")

    def flee(c: Commander) -> list[Event]:
        return [track("T-8", at=(64.5, 21.0)), telemetry()]

    published = await run_orders(
        commander,
        [telemetry(), track("T-8", at=(65.85, 21.10)), follow],
        options={"track_replan_s": 0.05},
        after=flee,
        until=lambda s: any(x.status is OrderState.FAILED for x in s),
    )
    assert states(published) == ["accepted", "executing", "failed"]
    assert published[-1].check == "geofence"
    assert published[-1].reason is not None
    assert published[-1].reason.startswith("the track moved to 64.50000, 21.00000: the route")
    assert len(commander.uploads) == 1  # nothing went up for the refused orbit


def test_order_status_round_trips_as_json() -> None:
    status = OrderStatus(
        event_id="slb-order-X-rejected",
        order_event_id="slb-order-X",
        order_id="X",
        source="brigade-slb",
        time=NOW,
        status=OrderState.REJECTED,
        check="terrain",
        reason="commanded 500.0 m MSL is below the floor",
    )
    assert event_adapter.validate_json(status.model_dump_json()) == status


def test_a_fence_of_two_corners_is_a_config_error() -> None:
    with pytest.raises(ValueError, match="at least 3"):
        OrdersConfig.model_validate({"geofence": FENCE[:2]})
    with pytest.raises(ValueError, match=r"airframe_geofences\n.*F26E-001: a fence needs 3"):
        OrdersConfig.model_validate({"airframe_geofences": {"F26E-001": FENCE[:2]}})


@pytest.mark.anyio
async def test_track_target_naming_a_live_track_flies_to_the_track() -> None:
    commander = Commander()
    seen = Track.model_validate(
        {
            "event_id": "T-7-1",
            "track_id": "T-7",
            "time": NOW,
            "object_class": "tank",
            "confidence": 0.9,
            "position": {"lat_deg": 65.87, "lon_deg": 21.15},
            "cep50_m": 10.0,
            "cep90_m": 20.0,
            "first_seen": NOW,
            "last_seen": NOW,
        }
    )
    tasked = order(task=OrderTask.TRACK_TARGET, track_id="T-7")
    await run_orders(
        commander,
        [telemetry(), seen, tasked],
        until=lambda s: any(x.status is OrderState.EXECUTING for x in s),
    )
    ((_, items),) = commander.uploads
    assert {(i.lat_deg, i.lon_deg) for i in items} == {(65.87, 21.15)}


@pytest.mark.anyio
async def test_track_target_naming_a_merged_track_flies_to_its_survivor() -> None:
    commander = Commander()

    def seen(track_id: str, lat: float, **extra: object) -> Track:
        return Track.model_validate(
            {
                "event_id": f"{track_id}-{extra.get('status', 'updated')}",
                "track_id": track_id,
                "time": NOW,
                "object_class": "tank",
                "confidence": 0.9,
                "position": {"lat_deg": lat, "lon_deg": 21.15},
                "cep50_m": 10.0,
                "cep90_m": 20.0,
                "first_seen": NOW,
                "last_seen": NOW,
                **extra,
            }
        )

    events = [
        telemetry(),
        seen("T-7", 65.87),
        seen("T-8", 65.871),
        seen("T-8", 65.871, status="merged", merged_into="T-7"),
        seen("T-7", 65.872),
        order(task=OrderTask.TRACK_TARGET, track_id="T-8"),
    ]
    await run_orders(
        commander, events, until=lambda s: any(x.status is OrderState.EXECUTING for x in s)
    )
    ((_, items),) = commander.uploads
    assert {(i.lat_deg, i.lon_deg) for i in items} == {(65.872, 21.15)}


def test_the_processors_speak_no_mavlink() -> None:
    """Orders are intents: command numbers, modes and mission items are the fleet's choice."""
    root = Path(__file__).resolve().parents[2] / "processors"
    for path in root.glob("*.py"):
        text = path.read_text()
        assert "MAV_CMD" not in text, path
        assert "gateway.fleet" not in text, path
        assert "pymavlink" not in text, path
