"""A sink contract check that third-party sink authors run in their own tests.

``check_sink(MySink, {"option": ...})`` builds the sink the way the gateway does and checks,
with real calls on a real event loop, what the gateway relies on (docs/writing-a-sink.md):
a strict, frozen config model; ``name``; ``kinds`` a non-empty frozenset of ``EventKind``;
``aclose`` safe before ``open``; ``open``, ``send`` of an empty batch and of one event of
every kind it accepts, and ``aclose``, each within a deadline and without blocking the event
loop. A failure raises ``ContractViolation`` saying which rule and what was found.

It is synchronous (it runs its own event loop), so call it from a plain test function::

    def test_my_sink_keeps_the_contract(tmp_path):
        check_sink(MySink, {"path": str(tmp_path / "out")})
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping, Sequence
from datetime import UTC, datetime
from typing import Any

import anyio
import anyio.lowlevel
from pydantic import ValidationError

from gateway.c2.sink import Sink, SinkConfig
from gateway.events import (
    BlueForce,
    Deconfliction,
    Detection,
    EffectorOption,
    Event,
    EventKind,
    FiveLineOrder,
    Handoff,
    HopEvent,
    HopReason,
    LinkState,
    OrderArea,
    OrderState,
    OrderStatus,
    OrderTask,
    Position,
    Sensor,
    Telemetry,
    Track,
    VideoFrameMetadata,
)

__all__ = ["ContractViolation", "check_sink", "sample_events"]

#: The event loop may not be held longer than this by one sink call.
MAX_BLOCK_S = 0.1
_TICK_S = 0.005


class ContractViolation(AssertionError):
    """Raised by ``check_sink`` when a sink breaks a rule of the sink contract."""


def sample_events(kinds: frozenset[EventKind]) -> list[Event]:
    """One valid event of each kind in ``kinds``, in ``EventKind`` order."""
    t = datetime(2026, 11, 22, 12, 0, 0, tzinfo=UTC)
    where = Position(lat_deg=65.8252, lon_deg=21.6886, alt_msl_m=250.0)
    track = Track(
        event_id="c-trk",
        track_id="T1",
        time=t,
        object_class="uav",
        confidence=0.8,
        position=where,
        cep50_m=10.0,
        cep90_m=18.0,
        first_seen=t,
        last_seen=t,
    )
    every: dict[EventKind, Event] = {
        EventKind.TELEMETRY: Telemetry(
            event_id="c-tel", airframe="F26E-001", time=t, position=where
        ),
        EventKind.LINK_STATE: LinkState(
            event_id="c-link",
            airframe="F26E-001",
            time=t,
            link="starlink",
            is_up=True,
            is_active=True,
            loss_pct=0.0,
            reason="heard",
        ),
        EventKind.DETECTION: Detection(
            event_id="c-det",
            airframe="F26E-001",
            time=t,
            sensor=Sensor.EO,
            object_class="uav",
            confidence=0.9,
            position=where,
            sigma_h_m=15.0,
        ),
        EventKind.TRACK: track,
        EventKind.BLUE_FORCE: BlueForce(
            event_id="c-bf", uid="ANDROID-1", time=t, position=where, source="cot"
        ),
    }
    every[EventKind.HANDOFF] = Handoff(
        event_id="c-ho",
        handoff_id="c-ho",
        time=t,
        battery="GUTE-1",
        battery_position=Position(lat_deg=59.3400, lon_deg=18.0500),
        track=track,
        range_m=1200.0,
        bearing_deg=45.0,
        recommended_effector="TRACKFIRE_30MM",
        options=(
            EffectorOption(
                effector="TRACKFIRE_30MM", deconfliction_clear=True, danger_close_m=400.0
            ),
        ),
        deconfliction=Deconfliction(clear=True, blue_units_considered=0),
    )
    every[EventKind.VIDEO_FRAME_METADATA] = VideoFrameMetadata(
        event_id="c-vfm",
        airframe="F26E-001",
        time=t,
        sensor_position=Position(lat_deg=59.3300, lon_deg=18.0600, alt_msl_m=600.0),
        heading_deg=87.5,
        pitch_deg=-2.5,
        roll_deg=3.0,
        hfov_deg=12.5,
        vfov_deg=7.0,
        sensor_azimuth_deg=45.0,
        sensor_elevation_deg=-30.0,
        sensor_roll_deg=0.0,
        frame_centre=where,
        frame_centre_source="camera",
        slant_range_m=1250.0,
        target_width_m=274.0,
    )
    every[EventKind.ORDER] = FiveLineOrder(
        event_id="slb-order-c-1",
        order_id="c-1",
        source="slb",
        time=t,
        task=OrderTask.OBSERVE_POINT,
        location=OrderArea(point=where),
    )
    every[EventKind.HOP] = HopEvent(
        event_id="c-hop",
        airframe="F26E-001",
        time=t,
        schedule_id=0x1234ABCD,
        is_gateway_schedule=True,
        slot=2,
        frequency_hz=2_435_000_000.0,
        reason=HopReason.JAMMED,
        hop_count=41_000,
        rssi_dbm=-62.0,
        interference_dbm=-31.0,
    )
    every[EventKind.ORDER_STATUS] = OrderStatus(
        event_id="slb-order-c-1-rejected",
        order_event_id="slb-order-c-1",
        order_id="c-1",
        source="slb",
        airframe="F26E-001",
        time=t,
        status=OrderState.REJECTED,
        check="geofence",
        reason="geofence: the point 59.33000, 18.06000 is outside the fence",
    )
    return [every[kind] for kind in EventKind if kind in kinds]


def check_sink(
    factory: Any,
    options: Mapping[str, Any] | None = None,
    *,
    name: str = "contract",
    deadline_s: float = 10.0,
    events: Sequence[Event] | None = None,
) -> Sink:
    """Build ``factory`` (a sink class) with ``options`` and check the contract; the sink.

    ``events`` replaces the sample events (``sample_events(sink.kinds)``). Raises
    ``ContractViolation`` for the first rule broken.
    """
    model = getattr(factory, "config_model", None)
    if not (isinstance(model, type) and issubclass(model, SinkConfig)):
        raise ContractViolation(f"{factory!r}: config_model must subclass gateway.SinkConfig")
    try:
        model.model_validate({"no_such_option_anywhere": 1})
    except ValidationError:
        pass
    else:
        raise ContractViolation(f"{model.__name__}: unknown options must be rejected")
    config = model.model_validate(dict(options or {}))
    sink = factory(name, config)
    if not isinstance(sink, Sink):
        raise ContractViolation(f"{factory!r}: builds {sink!r}, which lacks Sink's members")
    if sink.name != name:
        raise ContractViolation(f"sink.name is {sink.name!r}, expected the given {name!r}")
    kinds: object = sink.kinds
    if not (
        isinstance(kinds, frozenset) and kinds and all(isinstance(k, EventKind) for k in kinds)
    ):
        raise ContractViolation(f"kinds must be a non-empty frozenset of EventKind, got {kinds!r}")
    batch = list(events) if events is not None else sample_events(kinds)
    anyio.run(_exercise, sink, batch, deadline_s)
    return sink


async def _exercise(sink: Sink, batch: list[Event], deadline_s: float) -> None:
    await _timed("aclose() before open()", sink.aclose, deadline_s)
    await _timed("open()", sink.open, deadline_s)
    await _timed("send([])", lambda: sink.send([]), deadline_s)
    await _timed(f"send() of {len(batch)} events", lambda: sink.send(batch), deadline_s)
    await _timed("aclose()", sink.aclose, deadline_s)


async def _timed(what: str, call: Callable[[], Awaitable[None]], deadline_s: float) -> None:
    """Run ``call`` under ``deadline_s`` while a ticker measures how long the loop is held."""
    longest = 0.0
    last = anyio.current_time()

    def measure() -> None:
        nonlocal longest, last
        now = anyio.current_time()
        longest = max(longest, now - last - _TICK_S)
        last = now

    async def tick() -> None:
        while True:
            await anyio.sleep(_TICK_S)
            measure()

    try:
        with anyio.fail_after(deadline_s):
            async with anyio.create_task_group() as tg:
                tg.start_soon(tick)
                await anyio.lowlevel.checkpoint()  # the ticker starts before the call
                last = anyio.current_time()
                await call()
                measure()  # a call that blocked and then returned gave the ticker no turn
                tg.cancel_scope.cancel()
    except TimeoutError as exc:
        raise ContractViolation(f"{what} did not return within {deadline_s} s") from exc
    if longest > MAX_BLOCK_S:
        raise ContractViolation(
            f"{what} blocked the event loop for {longest:.3f} s (limit {MAX_BLOCK_S} s): "
            "run blocking work with anyio.to_thread.run_sync"
        )
