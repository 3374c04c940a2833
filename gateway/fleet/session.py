"""One airframe, in both directions: its links, its state, its message handlers, its commands.

``AirframeSession`` holds what the gateway knows of one airframe: its configured links (the
only ones that may speak for it) and the peer that last authenticated on each, link health
and failover, de-duplication, the passthrough, the normalised state, and an extensible
message table (``on(name, handler)``: telemetry, detections and COMMAND_ACK are registered by
ingest; camera, gimbal, mission and hop messages join the same way). A message may have
several handlers, called in the order they were registered; registering the same handler for
the same message twice is an error, never a silent replacement.

The session owns accept-and-dispatch: ``Ingest`` authenticates a frame and finds its
airframe, then the session takes it: ``accept`` (an authenticated frame names the peer on
that link and keeps the link alive; de-duplication across the airframe's links; the
passthrough) and ``dispatch`` (the handlers). Its state is private: others read it through
properties and change it only through these methods.

Outbound, ``send`` puts raw MAVLink on the airframe's active link in the link's mode (the
fleet's uplink, ``Fleet.send``, given as ``transmit``), and ``command_long`` sends a
COMMAND_LONG and waits for the COMMAND_ACK with the same command id: correlated, under a
timeout, retried with an incremented ``confirmation`` field as MAVLink's command protocol
asks, and reported as a ``CommandResult`` (result, attempts, latency) that ``status()`` shows.
"""

from __future__ import annotations

import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import anyio
import structlog

from gateway.config import AirframeConfig
from gateway.errors import LinkUnavailable
from gateway.fleet.dialect import fischer_detection_ack
from gateway.fleet.linkhealth import LinkHealth
from gateway.fleet.mavlink import MavMessage, dialect
from gateway.fleet.normalise import AirframeState
from gateway.fleet.security.signing import SigningVerifier

__all__ = ["AirframeSession", "CommandResult", "Handler", "Transmit"]

log = structlog.get_logger(__name__)

Handler = Callable[["AirframeSession", str, MavMessage], None]
"""Called with the session, the link label and one accepted, de-duplicated message."""

Transmit = Callable[[str, bytes], Awaitable[None]]

#: Our identity on the MAVLink network when the gateway itself commands: a ground station.
GATEWAY_SYSID = 255
#: MAV_COMP_ID_ONBOARD_COMPUTER: not 190, which QGroundControl and Mission Planner use, so a
#: ground station on the passthrough and the gateway are two components, never confused.
GATEWAY_COMPID = 191

_RESULT_NAMES: dict[int, str] = {
    int(key): str(entry.name) for key, entry in dialect.enums["MAV_RESULT"].items()
}
_MAV_RESULT_IN_PROGRESS = 5
_SIGNED_V2 = 0xFD  # MAVLink 2's start byte (a frame that may be signed)
_MAV_AUTOPILOT_INVALID = 8  # a GCS, a companion or a peripheral: not the flight controller
_DEDUP_PRUNE_EVERY = 1024
#: Builds message objects (``*_encode``); each frame is packed by ``encode`` with the
#: session's own sequence number.
_BUILDER = dialect.MAVLink(None, srcSystem=GATEWAY_SYSID, srcComponent=GATEWAY_COMPID)


@dataclass(frozen=True, slots=True)
class CommandResult:
    """How one command ended: acknowledged (``result`` is a MAV_RESULT) or timed out."""

    command: int
    result: int | None
    attempts: int
    latency_s: float | None
    """From the last attempt's send to its COMMAND_ACK."""

    @property
    def is_accepted(self) -> bool:
        """True for MAV_RESULT_ACCEPTED (0)."""
        return self.result == 0

    @property
    def result_name(self) -> str:
        """``MAV_RESULT_ACCEPTED`` ..., or ``TIMEOUT``."""
        if self.result is None:
            return "TIMEOUT"
        return _RESULT_NAMES.get(self.result, str(self.result))


@dataclass(slots=True)
class _Pending:
    sent_mono: float
    done: anyio.Event = field(default_factory=anyio.Event)
    result: int | None = None
    acked_mono: float | None = None
    in_progress: bool = False
    progress: anyio.Event = field(default_factory=anyio.Event)


class AirframeSession:
    """Everything the gateway holds for one airframe; see the module docstring.

    Its state is its own: others read it through properties and change it only through
    methods (``accept``, ``forget_peer``, ``on``, ``command_long`` ...).
    """

    __slots__ = (
        "_commands_sent",
        "_commands_timed_out",
        "_config",
        "_handlers",
        "_health",
        "_inserts",
        "_labels",
        "_last_command",
        "_multilink",
        "_passthrough",
        "_peers",
        "_pending",
        "_recent",
        "_seq",
        "_state",
        "_transmit",
        "_verifier",
    )

    def __init__(
        self,
        config: AirframeConfig,
        state: AirframeState,
        health: LinkHealth,
        labels: frozenset[str] = frozenset(),
        verifier: SigningVerifier | None = None,
        *,
        transmit: Transmit | None = None,
    ) -> None:
        self._config = config
        self._state = state
        self._health = health
        self._labels = labels
        self._verifier = verifier
        self._transmit = transmit
        self._passthrough: Callable[[bytes], None] | None = None
        #: Frames heard lately (without a signature), for de-duplication across links.
        self._recent: dict[bytes, float] = {}
        self._inserts = 0
        #: Per link label, the peer that last sent an authenticated frame of this airframe.
        self._peers: dict[str, object] = {}
        self._handlers: dict[str, list[Handler]] = {}
        self._last_command: CommandResult | None = None
        self._commands_sent = 0
        self._commands_timed_out = 0
        self._pending: dict[int, _Pending] = {}
        self._seq = 0
        self._multilink = len(health.links) > 1

    @property
    def config(self) -> AirframeConfig:
        """The airframe's config."""
        return self._config

    @property
    def state(self) -> AirframeState:
        """The airframe's normalised state (updated by ingest's telemetry handler)."""
        return self._state

    @property
    def health(self) -> LinkHealth:
        """The health of the airframe's links, and which is active."""
        return self._health

    @property
    def labels(self) -> frozenset[str]:
        """The labels of the airframe's configured links: the only ones it may speak on."""
        return self._labels

    @property
    def verifier(self) -> SigningVerifier | None:
        """The airframe's signing verifier, None without a signing key."""
        return self._verifier

    @property
    def last_command(self) -> CommandResult | None:
        """How the last command ended, None before the first."""
        return self._last_command

    @property
    def commands_sent(self) -> int:
        """COMMAND_LONG frames sent, resends included."""
        return self._commands_sent

    @property
    def commands_timed_out(self) -> int:
        """Commands that got no COMMAND_ACK after every attempt."""
        return self._commands_timed_out

    @property
    def id(self) -> str:
        """The airframe's id from the config."""
        return self._config.id

    def set_transmit(self, transmit: Transmit) -> None:
        """Send what ``send`` is given through ``transmit(airframe, frames)`` from now on."""
        self._transmit = transmit

    def set_passthrough(self, forward: Callable[[bytes], None]) -> None:
        """Forward every accepted frame (raw MAVLink) to ``forward`` from now on."""
        self._passthrough = forward

    # -- accepting (ingest's hot path: no allocation beyond what a frame needs) ------------

    def peer(self, label: str) -> object | None:
        """The peer on link ``label`` that last sent an authenticated frame of this airframe."""
        return self._peers.get(label)

    def forget_peer(self, label: str, peer: object) -> None:
        """``peer`` (a closed stream connection) no longer speaks for the airframe on ``label``."""
        if self._peers.get(label) == peer:
            del self._peers[label]

    def accept(
        self,
        label: str,
        peer: object,
        authenticated: bool,
        trust: Callable[[object], None] | None,
        buf: bytes | bytearray,
        name: str,
        msg: MavMessage,
        now_mono: float,
    ) -> bool:
        """Take one frame of the airframe from ``peer`` on link ``label``, before dispatch.

        An ``authenticated`` frame is ``heard`` (a peer new on the link is also given to
        ``trust``); unsigned frames the config accepts prove nothing and are not. Then False
        for a frame already heard on another link within the de-duplication window (drop
        it); else it goes to the passthrough, a flight controller's HEARTBEAT names the
        autopilot's component, and True: dispatch it. One call per frame: ingest's hot path.
        """
        if authenticated:
            if self._peers.get(label) != peer:
                self._peers[label] = peer
                if trust is not None:
                    trust(peer)
            # Component id and sequence number from the header (MAVLink 2, else 1).
            if buf[0] == _SIGNED_V2:
                self._health.heard(label, buf[6], buf[4], now_mono)
            else:
                self._health.heard(label, buf[4], buf[2], now_mono)
        if self._multilink and self._duplicate(buf, now_mono):
            return False
        if self._passthrough is not None:
            self._passthrough(bytes(buf))
        if name == "HEARTBEAT" and msg.autopilot != _MAV_AUTOPILOT_INVALID:
            self._health.autopilot_compid = buf[6] if buf[0] == _SIGNED_V2 else buf[4]
        return True

    def _duplicate(self, buf: bytes | bytearray, now_mono: float) -> bool:
        """True if the same frame arrived on another link within the de-duplication window."""
        # A signature differs per link (its link id), so compare the frame without it.
        key = bytes(buf[:-13]) if buf[0] == _SIGNED_V2 and buf[2] & 1 else bytes(buf)
        window = self._config.dedup_window_s
        recent = self._recent
        seen = recent.get(key)
        if seen is not None and now_mono - seen < window:
            return True
        recent[key] = now_mono
        self._inserts += 1
        if self._inserts % _DEDUP_PRUNE_EVERY == 0:
            self._recent = {k: t for k, t in recent.items() if now_mono - t < window}
        return False

    def on(self, message: str, handler: Handler) -> None:
        """Also hand every accepted ``message`` (a MAVLink message name) to ``handler``.

        Handlers of one message are called in the order they were registered. ``ValueError``
        if ``handler`` already handles ``message`` (it would be called twice per message).
        """
        handlers = self._handlers.setdefault(message, [])
        if handler in handlers:
            raise ValueError(f"airframe {self.id}: {handler!r} already handles {message}")
        handlers.append(handler)

    def handlers(self, message: str) -> tuple[Handler, ...]:
        """The handlers of ``message``, in the order they are called."""
        return tuple(self._handlers.get(message, ()))

    def dispatch(self, label: str, name: str, msg: MavMessage) -> None:
        """Hand an accepted message to each of its handlers; unhandled messages are ignored.

        A handler that raises does not keep the message from the others: every handler is
        called, then the first exception is raised for the caller to count.
        """
        failure: Exception | None = None
        for handler in self._handlers.get(name, ()):
            try:
                handler(self, label, msg)
            except Exception as exc:  # noqa: BLE001 - raised below, after the other handlers
                failure = failure or exc
        if failure is not None:
            raise failure

    # -- outbound ---------------------------------------------------------------------------

    async def send(self, frames: bytes) -> None:
        """Send raw MAVLink ``frames`` to the airframe; ``LinkError`` if it cannot go."""
        if self._transmit is None:
            raise LinkUnavailable(self.id, "the session has no transmit path")
        await self._transmit(self.id, frames)

    def on_command_ack(self, _session: AirframeSession, _label: str, msg: MavMessage) -> None:
        """The COMMAND_ACK handler: resolve the command waiting for it, if any."""
        # An ACK addressed to someone else (a ground station on the passthrough) is not ours.
        target_system = int(getattr(msg, "target_system", 0) or 0)
        target_component = int(getattr(msg, "target_component", 0) or 0)
        if target_system not in (0, GATEWAY_SYSID) or target_component not in (0, GATEWAY_COMPID):
            return
        pending = self._pending.get(int(msg.command))
        if pending is None or pending.done.is_set():
            return
        if int(msg.result) == _MAV_RESULT_IN_PROGRESS:
            # Accepted and running (a calibration ...): stop resending, wait for the result.
            pending.in_progress = True
            pending.progress.set()
            return
        pending.result = int(msg.result)
        pending.acked_mono = time.monotonic()
        pending.done.set()

    def encode_detection_ack(self, detection_id: int, time_usec: int, result: int) -> bytes:
        """A FISCHER_DETECTION_ACK frame for one of this airframe's detections."""
        return self.encode(
            fischer_detection_ack(time_usec, detection_id, self._config.sysid, 1, result)
        )

    def encode(self, msg: MavMessage) -> bytes:
        """``msg`` (a pymavlink message) as a frame from the gateway, in this session's
        sequence numbering."""
        mav = dialect.MAVLink(None, srcSystem=GATEWAY_SYSID, srcComponent=GATEWAY_COMPID)
        mav.seq = self._seq
        self._seq = (self._seq + 1) % 256
        return bytes(msg.pack(mav))

    def pack(self, name: str, *fields: Any) -> bytes:
        """One frame of message ``name`` (``mission_count`` ...) from the gateway's identity."""
        return self.encode(getattr(_BUILDER, f"{name}_encode")(*fields))

    def _encode_command_long(
        self, command: int, params: tuple[float, ...], confirmation: int
    ) -> bytes:
        padded = (*params, *(0.0,) * (7 - len(params)))[:7]
        return self.pack("command_long", self.config.sysid, 1, command, confirmation, *padded)

    async def command_long(
        self,
        command: int,
        *params: float,
        timeout_s: float = 1.5,
        retries: int = 2,
        in_progress_timeout_s: float = 60.0,
    ) -> CommandResult:
        """Send COMMAND_LONG ``command`` and wait for its COMMAND_ACK.

        Retries ``retries`` times after a timeout (``confirmation`` counts the attempts); once
        the airframe says MAV_RESULT_IN_PROGRESS it is not resent, and the final ACK is awaited
        for up to ``in_progress_timeout_s``. Returns the ``CommandResult``; raises
        ``LinkError`` if it cannot be sent at all. One command per id at a time: a second
        ``command_long`` with the same id waits its turn. MAVLink ACKs carry no request id, so
        an ACK that comes after its command timed out can answer the next one with that id.
        """
        if retries < 0 or timeout_s <= 0:
            raise ValueError("expected retries >= 0 and timeout_s > 0")
        while command in self._pending:
            await self._pending[command].done.wait()
        attempts = 0
        pending = _Pending(time.monotonic())
        self._pending[command] = pending
        try:
            for confirmation in range(retries + 1):
                attempts += 1
                pending.sent_mono = time.monotonic()
                await self.send(self._encode_command_long(command, params, confirmation))
                self._commands_sent += 1
                with anyio.move_on_after(timeout_s):
                    await _first(pending.done, pending.progress)
                if pending.in_progress and not pending.done.is_set():
                    with anyio.move_on_after(in_progress_timeout_s):
                        await pending.done.wait()
                if pending.done.is_set() or pending.in_progress:
                    break
            if pending.result is None:
                self._commands_timed_out += 1
                log.warning(
                    "command_timed_out",
                    airframe=self.id,
                    command=command,
                    attempts=attempts,
                    timeout_s=timeout_s,
                )
        finally:
            pending.done.set()
            del self._pending[command]
        latency = None if pending.acked_mono is None else pending.acked_mono - pending.sent_mono
        result = CommandResult(command, pending.result, attempts, latency)
        self._last_command = result
        return result

    def command_status(self) -> dict[str, Any]:
        """The command side of the session for /status."""
        last = self._last_command
        return {
            "commands_sent": self._commands_sent,
            "commands_timed_out": self._commands_timed_out,
            "last_command": None
            if last is None
            else {
                "command": last.command,
                "result": last.result_name,
                "attempts": last.attempts,
                "latency_s": None if last.latency_s is None else round(last.latency_s, 4),
            },
        }


async def _first(*events: anyio.Event) -> None:
    """Return as soon as one of ``events`` is set."""
    async with anyio.create_task_group() as tg:

        async def wait(event: anyio.Event) -> None:
            await event.wait()
            tg.cancel_scope.cancel()

        for event in events:
            tg.start_soon(wait, event)
