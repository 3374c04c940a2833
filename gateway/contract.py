"""The plugin contracts in one place, with the checks plugin authors run in their own tests.

A sink, a source and a processor are each a small class found through an entry point
(docs/writing-a-sink.md); this module names their protocols and option base classes
(``Sink``/``SinkConfig``, ``Source``/``SourceConfig``, ``Processor``/``ProcessorConfig``) and
ships one checker for each. A checker builds the component from its options the way the
gateway does and runs it, with real calls on a real event loop, against what the gateway
relies on: a strict, frozen options model; ``name`` kept; each call returning within a
deadline without holding the event loop for more than ``MAX_BLOCK_S``; a long-running ``run``
that reports ``started``, ends promptly when cancelled and publishes only valid events. A
failure raises ``ContractViolation`` saying which rule and what was found.

- ``check_sink``: ``kinds`` a non-empty frozenset of ``EventKind``; ``aclose`` safe before
  ``open``; ``open``, ``send`` of an empty batch and of one event of every kind it accepts,
  and ``aclose``; a ``send_now`` (optional, ``gateway.c2.sink.SendsNow``) a plain method
  that, given the same events, returns how many it delivered (an ``int`` from 0 to their
  number) without holding the loop.
- ``check_source``: ``status()`` a dict before, during and after ``run``; ``drive`` (yours)
  gives the running source its input.
- ``check_processor``: ``kinds`` as for a sink; ``extension_events`` (if declared) maps type
  names to pydantic models with a JSON Schema; one sample event of every kind it consumes is
  fed to its ``run``; each ``Extension`` it publishes has a declared type and valid ``data``.

The checkers are synchronous (each runs its own event loop), so call them from a plain test
function::

    def test_my_sink_keeps_the_contract(tmp_path):
        check_sink(MySink, {"path": str(tmp_path / "out")})
"""

from __future__ import annotations

import inspect
import json
import threading
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Generic, TypeVar

import anyio
import anyio.abc
import anyio.lowlevel
from pydantic import BaseModel, ValidationError

from gateway.c2.sink import Sink, SinkConfig
from gateway.c2.source import Source, SourceConfig
from gateway.clock import utc_now
from gateway.events import (
    BlueForce,
    Deconfliction,
    Detection,
    EffectorOption,
    Event,
    EventKind,
    Extension,
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
    declared_extensions,
    event_adapter,
)
from gateway.flow.processor import Processor, ProcessorConfig, Publish

__all__ = [
    "MAX_BLOCK_S",
    "ContractRun",
    "ContractViolation",
    "LoopBlocked",
    "Processor",
    "ProcessorConfig",
    "Publish",
    "Sink",
    "SinkConfig",
    "Source",
    "SourceConfig",
    "check_processor",
    "check_sink",
    "check_source",
    "sample_events",
]

#: The event loop may not be held longer than this by one sink call.
MAX_BLOCK_S = 0.1
_TICK_S = 0.005


#: At most this many published events are kept (and checked) by one check.
MAX_PUBLISHED = 10_000

T = TypeVar("T")


class ContractViolation(AssertionError):
    """Raised by a checker when a plugin breaks a rule of its contract."""


class LoopBlocked(ContractViolation):
    """A call held the event loop longer than ``MAX_BLOCK_S``.

    Measured on the wall clock, so a loaded machine that deschedules the process looks the
    same: each checker runs a fresh plugin once more before it reports this, and a plugin
    that truly blocks does it again.
    """


def _twice_if_blocked(check: Callable[[], T]) -> T:
    """``check()``, run once more if it found the loop blocked (see ``LoopBlocked``)."""
    try:
        return check()
    except LoopBlocked:
        return check()


@dataclass(frozen=True, slots=True)
class ContractRun(Generic[T]):
    """What a passed ``check_source`` or ``check_processor`` leaves for further asserts."""

    component: T
    """The instance that was checked (its ``status()``, counters ...)."""
    published: tuple[Event, ...]
    """Every event it published, in order (the first ``MAX_PUBLISHED``)."""


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
    every[EventKind.EXTENSION] = Extension(
        event_id="c-ext",
        type="example.sample",
        time=t,
        publisher="contract",
        data={"note": "a sample extension event", "values": [1, 2.5, None]},
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
    config = _config(factory, SinkConfig, "gateway.SinkConfig", options)
    sink = factory(name, config)
    if not isinstance(sink, Sink):
        raise ContractViolation(f"{factory!r}: builds {sink!r}, which lacks Sink's members")
    send_now = getattr(sink, "send_now", None)
    if send_now is not None and (not callable(send_now) or inspect.iscoroutinefunction(send_now)):
        raise ContractViolation(
            f"sink.send_now is {send_now!r}: it must be a plain (not async) method that "
            "returns how many of the batch it delivered"
        )
    if sink.name != name:
        raise ContractViolation(f"sink.name is {sink.name!r}, expected the given {name!r}")
    kinds = _kinds(sink.kinds)
    batch = list(events) if events is not None else sample_events(kinds)
    try:
        anyio.run(_exercise, sink, batch, deadline_s)
    except LoopBlocked:  # once more, on a fresh sink (see LoopBlocked)
        fresh: Sink = factory(name, config)
        anyio.run(_exercise, fresh, batch, deadline_s)
        return fresh
    return sink


async def _exercise(sink: Sink, batch: list[Event], deadline_s: float) -> None:
    await _timed("aclose() before open()", sink.aclose, deadline_s)
    await _timed("open()", sink.open, deadline_s)
    await _timed("send([])", lambda: sink.send([]), deadline_s)
    await _timed(f"send() of {len(batch)} events", lambda: sink.send(batch), deadline_s)
    send_now = getattr(sink, "send_now", None)
    if send_now is not None:
        sent: list[object] = []

        async def now() -> None:
            sent.append(send_now(batch))

        await _timed(f"send_now() of {len(batch)} events", now, deadline_s)
        count = sent[0]
        if type(count) is not int or not 0 <= count <= len(batch):
            raise ContractViolation(
                f"send_now() of {len(batch)} events returned {count!r}: expected an int "
                f"from 0 to {len(batch)} (how many it delivered)"
            )
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
        raise LoopBlocked(
            f"{what} blocked the event loop for {longest:.3f} s (limit {MAX_BLOCK_S} s): "
            "run blocking work with anyio.to_thread.run_sync"
        )


def check_source(
    factory: Any,
    options: Mapping[str, Any] | None = None,
    *,
    name: str = "contract",
    drive: Callable[[Any], Awaitable[None]] | None = None,
    run_s: float = 0.2,
    deadline_s: float = 10.0,
    clock: Callable[[], datetime] = utc_now,
) -> ContractRun[Source]:
    """Build ``factory`` (a source class) with ``options``, run it and check the contract.

    The source runs until it reports ``started``; then ``drive(source)``, if given, gives it
    input (send it a datagram, connect to its port); then it runs ``run_s`` more seconds and
    is cancelled. Raises ``ContractViolation`` for the first rule broken; returns the source
    and what it published.
    """
    config = _config(factory, SourceConfig, "gateway.SourceConfig", options)

    def once() -> ContractRun[Source]:
        published = _Published()
        source = factory(name, config, published, clock=clock)
        if not isinstance(source, Source):
            raise ContractViolation(f"{factory!r}: builds {source!r}, which lacks Source's members")
        if source.name != name:
            raise ContractViolation(f"source.name is {source.name!r}, expected the given {name!r}")
        _check_status(source, "before run()")

        async def exercise(phase: _Phase) -> None:
            async def input_then_wait() -> None:
                if drive is not None:
                    phase.enter("drive(source)")
                    with anyio.fail_after(deadline_s):
                        await drive(source)
                _check_status(source, "while it runs")
                await anyio.sleep(run_s)

            await _exercise_run(phase, source.run, input_then_wait, deadline_s)

        _nothing_published_yet(published)
        _guarded(exercise, published, deadline_s)
        _check_status(source, "after run() ended")
        return ContractRun(source, published.kept())

    return _twice_if_blocked(once)


def check_processor(
    factory: Any,
    options: Mapping[str, Any] | None = None,
    *,
    name: str = "contract",
    events: Sequence[Event] | None = None,
    settle_s: float = 0.2,
    deadline_s: float = 10.0,
) -> ContractRun[Processor]:
    """Build ``factory`` (a processor class) with ``options``, feed it and check the contract.

    Its ``run`` gets a stream holding ``events`` (default: ``sample_events(processor.kinds)``);
    once it has read them all and ``settle_s`` has passed, it is cancelled, as at shutdown.
    Raises ``ContractViolation`` for the first rule broken; returns the processor and what it
    published.
    """
    config = _config(factory, ProcessorConfig, "gateway.ProcessorConfig", options)

    def once() -> ContractRun[Processor]:
        processor = factory(name, config)
        if not isinstance(processor, Processor):
            raise ContractViolation(
                f"{factory!r}: builds {processor!r}, which lacks Processor's members"
            )
        if processor.name != name:
            raise ContractViolation(
                f"processor.name is {processor.name!r}, expected the given {name!r}"
            )
        batch = list(events) if events is not None else sample_events(_kinds(processor.kinds))
        published = _Published(_declared(factory))

        async def exercise(phase: _Phase) -> None:
            # Unbuffered: each send returns once run() has taken the event.
            send, receive = anyio.create_memory_object_stream[Event](0)

            async def run(*, task_status: anyio.abc.TaskStatus[None]) -> None:
                await processor.run(receive, published, task_status=task_status)

            async def feed_then_wait() -> None:
                phase.enter(f"reading the {len(batch)} events fed to run()")
                with anyio.fail_after(deadline_s):
                    for event in batch:
                        await send.send(event)
                await anyio.sleep(settle_s)

            with send, receive:
                await _exercise_run(phase, run, feed_then_wait, deadline_s)

        _guarded(exercise, published, deadline_s)
        return ContractRun(processor, published.kept())

    return _twice_if_blocked(once)


def _config(
    factory: Any, base: type[BaseModel], base_name: str, options: Mapping[str, Any] | None
) -> Any:
    """The validated options of ``factory``; its model must subclass ``base`` and be strict."""
    model = getattr(factory, "config_model", None)
    if not (isinstance(model, type) and issubclass(model, base)):
        raise ContractViolation(f"{factory!r}: config_model must subclass {base_name}")
    try:
        model.model_validate({"no_such_option_anywhere": 1})
    except ValidationError:
        pass
    else:
        raise ContractViolation(f"{model.__name__}: unknown options must be rejected")
    return model.model_validate(dict(options or {}))


def _declared(factory: Any) -> dict[str, type[BaseModel]]:
    """The processor's ``extension_events``, each with a model that gives a JSON Schema."""
    try:
        declared = declared_extensions(factory)
    except ValueError as exc:
        raise ContractViolation(f"{factory!r}: {exc}") from None
    for name, model in declared.items():
        try:
            model.model_json_schema()
        except Exception as exc:  # noqa: BLE001 - pydantic raises several kinds here
            raise ContractViolation(
                f"extension_events[{name!r}]: {model.__name__} has no JSON Schema: {exc}"
            ) from None
    return declared


def _kinds(kinds: object) -> frozenset[EventKind]:
    if not (
        isinstance(kinds, frozenset) and kinds and all(isinstance(k, EventKind) for k in kinds)
    ):
        raise ContractViolation(f"kinds must be a non-empty frozenset of EventKind, got {kinds!r}")
    return kinds


def _check_status(source: Source, when: str) -> None:
    status: object = source.status()
    if not isinstance(status, dict):
        raise ContractViolation(f"status() {when} must return a dict, got {status!r}")
    try:
        json.dumps(status, default=str)
    except (TypeError, ValueError) as exc:
        raise ContractViolation(f"status() {when} does not serialise to JSON: {exc}") from exc


class _Phase:
    """What the check is waiting for, and since when (read by the watchdog thread)."""

    def __init__(self) -> None:
        self.what = "starting the event loop"
        self.since = time.monotonic()

    def enter(self, what: str) -> None:
        self.what, self.since = what, time.monotonic()


class _Published:
    """The ``publish`` given to the plugin: keeps, and checks, every event it is handed."""

    def __init__(self, extensions: Mapping[str, type[BaseModel]] | None = None) -> None:
        self.extensions = dict(extensions or {})
        self.events: list[Event] = []
        self.problem: str | None = None
        self.loop_thread: int | None = None

    def __call__(self, event: Event) -> bool:
        if self.problem is None:
            self.problem = self._check(event)
        if len(self.events) < MAX_PUBLISHED:
            self.events.append(event)
        return True

    def _check(self, event: object) -> str | None:
        if threading.get_ident() != self.loop_thread:
            return "publish() was called from outside the event loop's thread"
        if not isinstance(event, BaseModel):
            return f"published {event!r}, which is not a gateway event"
        try:
            again = event_adapter.validate_json(event.model_dump_json())
        except (ValidationError, ValueError, TypeError) as exc:
            return f"published an invalid {type(event).__name__}: {exc}"
        if again != event:
            return f"published a {type(event).__name__} that does not survive JSON: {event!r}"
        if isinstance(event, Extension):
            return self._check_extension(event)
        return None

    def _check_extension(self, event: Extension) -> str | None:
        model = self.extensions.get(event.type)
        if model is None:
            return (
                f"published an Extension of type {event.type!r}, which its extension_events "
                f"do not declare (declared: {sorted(self.extensions)})"
            )
        try:
            model.model_validate(event.data)
        except ValidationError as exc:
            return (
                f"published an Extension {event.type!r} whose data {model.__name__} rejects: {exc}"
            )
        return None

    def kept(self) -> tuple[Event, ...]:
        return tuple(self.events)


def _nothing_published_yet(published: _Published) -> None:
    """Nothing may be published before ``run`` (from ``__init__``, say)."""
    if published.events:
        raise ContractViolation(
            f"published {len(published.events)} event(s) before run() was started"
        )


async def _exercise_run(
    phase: _Phase,
    run: Callable[..., Awaitable[None]],
    meanwhile: Callable[[], Awaitable[None]],
    deadline_s: float,
) -> None:
    """Start ``run`` as the gateway does, do ``meanwhile``, cancel it; check each step.

    Violations are raised once every task group has exited, so they arrive unwrapped.
    """
    ended: list[str] = []
    watch = _LoopWatch()

    async def supervised(*, task_status: anyio.abc.TaskStatus[None]) -> None:
        try:
            await run(task_status=task_status)
        except anyio.get_cancelled_exc_class():
            raise
        except Exception as exc:  # noqa: BLE001 - a plugin's bug, reported as a violation
            ended.append(f"raised {type(exc).__name__}: {exc}")
        else:
            ended.append("returned")

    problem: str | None = None
    error: Exception | None = None
    async with anyio.create_task_group() as outer:
        outer.start_soon(watch.tick)
        await anyio.lowlevel.checkpoint()
        async with anyio.create_task_group() as tg:
            phase.enter("run() calling task_status.started()")
            try:
                with anyio.fail_after(deadline_s):
                    await tg.start(supervised)
                await meanwhile()
            except TimeoutError:
                problem = f"{phase.what} did not happen within {deadline_s} s"
            except RuntimeError:  # the child ended without reporting started
                problem = f"run() {ended[0] if ended else 'ended'} before task_status.started()"
            except Exception as exc:  # noqa: BLE001 - the caller's drive: raised unwrapped below
                error = exc
            if problem is None and ended:
                problem = f"run() {ended[0]} before it was cancelled"
            phase.enter("run() ending after it was cancelled")
            cancelled_at = anyio.current_time()
            tg.cancel_scope.cancel()
        took = anyio.current_time() - cancelled_at
        outer.cancel_scope.cancel()
    if error is not None:
        raise error
    if problem is None and took > deadline_s:
        problem = f"{phase.what} did not happen within {deadline_s} s (it took {took:.3f} s)"
    if problem is None and ended:
        problem = f"run() {ended[0]} when it was cancelled"
    if problem is None and watch.longest > MAX_BLOCK_S:
        raise LoopBlocked(
            f"run() blocked the event loop for {watch.longest:.3f} s (limit {MAX_BLOCK_S} s): "
            "run blocking work with anyio.to_thread.run_sync"
        )
    if problem is not None:
        raise ContractViolation(problem)


class _LoopWatch:
    """Measures the longest time the event loop was held away from a ticking task."""

    def __init__(self) -> None:
        self.longest = 0.0

    async def tick(self) -> None:
        last = anyio.current_time()
        while True:
            await anyio.sleep(_TICK_S)
            now = anyio.current_time()
            self.longest = max(self.longest, now - last - _TICK_S)
            last = now


def _guarded(
    exercise: Callable[[_Phase], Awaitable[None]], published: _Published, deadline_s: float
) -> None:
    """Run ``exercise`` on its own event loop in a thread, so a run that never ends cannot
    hang the check: past twice the deadline in one phase, that phase is the violation (and
    the thread is left to end when it may)."""
    phase = _Phase()
    failure: list[BaseException] = []

    async def main() -> None:
        published.loop_thread = threading.get_ident()
        await exercise(phase)

    def target() -> None:
        try:
            anyio.run(main)
        except BaseException as exc:  # noqa: BLE001 - handed to the checking thread
            failure.append(exc)

    thread = threading.Thread(target=target, name="contract-check", daemon=True)
    thread.start()
    while thread.is_alive():
        thread.join(_TICK_S * 10)
        if thread.is_alive() and time.monotonic() - phase.since > 2 * deadline_s:
            raise ContractViolation(f"{phase.what} did not happen within {deadline_s} s")
    if failure:
        raise failure[0]
    if published.problem is not None:
        raise ContractViolation(published.problem)
