"""The ``nats`` sink: this node's detections and airframe states into JetStream.

Each event goes to ``fsg.<node>.<kind>.<airframe token>`` (``sinks.nats.subjects``) with
``Nats-Msg-Id`` = its event id, and the server's acknowledgement is awaited: a batch is
published at once (``publish_async``, pipelined) and ``send`` returns only when every publish
of it is acked,
so the runner confirms to the spool only acked events. Any failure (server unreachable, an
ack missing within ``request_timeout_s``) raises ``TransientSinkError``: the runner retries
the same batch, and the ids already stored are dropped by the stream's de-duplication
window. A node whose NATS is down so keeps working locally; the spool holds its detections
and they go out, in order, once the server answers again.

An event that came from another node (``origin_node`` set) is never published again: no
loops between nodes. Streams are created from the options, or checked when ops made them
(``create_streams: false``).
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Mapping, Sequence

import anyio
import structlog
from nats.aio.client import Client
from nats.errors import MaxPayloadError
from nats.js import JetStreamContext
from nats.js.api import PubAck
from pydantic import Field, field_validator

from gateway.c2.sink import SinkConfig
from gateway.errors import PermanentSinkError, TransientSinkError
from gateway.events import Event, EventKind
from gateway.ops.logsetup import RateLimit
from sinks.nats.connection import NatsServer, connect
from sinks.nats.streams import ensure_stream, events_stream, telemetry_stream
from sinks.nats.subjects import KIND_TOKENS, encode_event, subject_for

__all__ = ["NatsSink", "NatsSinkConfig"]

log = structlog.get_logger(__name__)

_KINDS = frozenset(KIND_TOKENS)


class NatsSinkConfig(SinkConfig, NatsServer):
    """Options of the ``nats`` sink: this node's server and the streams it publishes to."""

    kinds: frozenset[EventKind] = Field(
        default=_KINDS,
        min_length=1,
        description="What this node publishes: detection, telemetry, handoff, order_status.",
    )
    create_streams: bool = Field(
        default=True,
        description="Create this node's streams if missing; false: only check those ops made.",
    )
    max_age_h: float = Field(
        default=72.0, gt=0, le=24 * 365, description="How long detections are kept, hours."
    )
    max_bytes: int = Field(
        default=1 << 30, ge=1 << 20, description="Size cap of the detections stream (discard old)."
    )
    duplicate_window_s: float = Field(
        default=600.0,
        ge=10,
        le=86_400,
        description="De-duplication window by event id: longer than any outage plus retry.",
    )
    telemetry_max_age_s: float = Field(
        default=3600.0, ge=10, le=7 * 86_400, description="How long an airframe's state is kept."
    )

    @field_validator("kinds")
    @classmethod
    def _carried(cls, kinds: frozenset[EventKind]) -> frozenset[EventKind]:
        extra = kinds - _KINDS
        if extra:
            names = ", ".join(sorted(kind.value for kind in extra))
            carried = ", ".join(kind.value for kind in KIND_TOKENS)
            raise ValueError(f"kinds: {names} not carried between nodes ({carried})")
        return kinds


class NatsSink:
    """Publishes this node's events to its JetStream streams, acked and pipelined."""

    config_model = NatsSinkConfig

    def __init__(self, name: str, config: NatsSinkConfig) -> None:
        self.name = name
        self.config = config
        self._nc: Client | None = None
        self._js: JetStreamContext | None = None
        self._counts: Counter[str] = Counter()
        self._log_limit = RateLimit(interval_s=10.0)

    @property
    def kinds(self) -> frozenset[EventKind]:
        """detection, telemetry, handoff and order_status (or the subset configured)."""
        return self.config.kinds

    def environment_warnings(self) -> list[str]:
        """What ``check-config`` should say of this node's use of NATS."""
        cfg = self.config
        if cfg.tls is None and cfg.creds_file is None and cfg.token_file is None:
            return [
                "connects to its NATS server with no credentials (tls, creds_file or"
                " token_file): unless that server limits who may publish fsg."
                f"{cfg.node}.>, any of its clients can publish detections as this node"
                " (docs/scale-out.md, who may publish what)"
            ]
        return []

    def counts(self) -> Mapping[str, int]:
        """published, duplicate (already stored), relayed_skipped (another node's), failed."""
        return dict(self._counts)

    def status(self) -> dict[str, object]:
        """The node, the server URLs, whether connected, and the counts."""
        return {
            "node": self.config.node,
            "servers": list(self.config.servers),
            "connected": bool(self._nc is not None and self._nc.is_connected),
            "counts": dict(self._counts),
        }

    async def open(self) -> None:
        """Connect and create or check the streams; ``TransientSinkError`` if that fails."""
        cfg = self.config
        try:
            nc = await connect(cfg, self.name)
        except Exception as exc:  # nats raises its own and OSError: all mean "not now"
            raise TransientSinkError(
                f"sink {self.name}: cannot reach NATS at {', '.join(cfg.servers)}: {exc}",
                sink=self.name,
            ) from exc
        self._nc = nc
        js = nc.jetstream(timeout=cfg.request_timeout_s)
        try:
            if cfg.kinds - {EventKind.TELEMETRY}:
                wanted = events_stream(
                    cfg.node,
                    cfg.kinds,
                    cfg.max_age_h * 3600.0,
                    cfg.max_bytes,
                    cfg.duplicate_window_s,
                )
                await ensure_stream(js, wanted, create=cfg.create_streams)
            if EventKind.TELEMETRY in cfg.kinds:
                wanted = telemetry_stream(cfg.node, cfg.telemetry_max_age_s)
                await ensure_stream(js, wanted, create=cfg.create_streams)
        except Exception as exc:
            await self.aclose()
            raise TransientSinkError(
                f"sink {self.name}: streams of node {cfg.node}: {exc}", sink=self.name
            ) from exc
        self._js = js

    async def send(self, batch: Sequence[Event]) -> None:
        """Publish every event of this node in ``batch`` at once and await every ack."""
        if self._js is None:
            raise TransientSinkError(f"sink {self.name}: not open", sink=self.name)
        own: list[Event] = []
        for event in batch:
            if getattr(event, "origin_node", None) is not None:
                self._counts["relayed_skipped"] += 1
            else:
                own.append(event)
        if not own:
            return
        results = await self._publish_all(own)
        too_large: list[str] = []
        failure: BaseException | None = None
        for event, result in zip(own, results, strict=True):
            if isinstance(result, MaxPayloadError):
                too_large.append(event.event_id)
            elif isinstance(result, BaseException):
                failure = failure or result
            elif result.duplicate:
                self._counts["duplicate"] += 1
            else:
                self._counts["published"] += 1
        if failure is not None:
            if isinstance(failure, asyncio.CancelledError):
                raise failure
            self._counts["failed"] += 1
            raise TransientSinkError(
                f"sink {self.name}: publish to NATS not acknowledged: "
                f"{type(failure).__name__} {failure}",
                sink=self.name,
            )
        if too_large:
            raise PermanentSinkError(
                f"sink {self.name}: {len(too_large)} event(s) larger than the server's max_payload",
                sink=self.name,
                event_ids=too_large,
            )

    async def _publish_all(self, events: list[Event]) -> list[PubAck | BaseException]:
        """Publish ``events`` pipelined and wait for every ack, at most ``request_timeout_s``.

        ``publish_async`` futures have no deadline of their own (a server that dies leaves
        them pending for ever): what is not acked by then is cancelled and failed here, and
        the whole batch is sent again with the same ids.
        """
        js = self._js
        if js is None:
            raise TransientSinkError(f"sink {self.name}: not open", sink=self.name)
        node = self.config.node
        timeout = self.config.request_timeout_s
        futures: list[asyncio.Future[PubAck]] = []
        try:
            with anyio.fail_after(timeout):
                for event in events:
                    try:
                        future = await js.publish_async(
                            subject_for(node, event),
                            encode_event(event),
                            # No expected-stream header: it travels with the message into
                            # the aggregating node's stream, and 2.9 servers refuse it there.
                            headers={"Nats-Msg-Id": event.event_id},
                        )
                    except MaxPayloadError as exc:  # refused before sending: this one only
                        future = asyncio.get_running_loop().create_future()
                        future.set_exception(exc)
                    futures.append(future)
                await asyncio.wait(futures)
        except TimeoutError:
            pass
        finally:
            for future in futures:
                future.cancel()  # no-op for a done one; frees the client's slot otherwise
        results: list[PubAck | BaseException] = []
        for future in futures:
            if future.cancelled():
                results.append(TimeoutError(f"no ack within {timeout} s"))
            elif (error := future.exception()) is not None:
                results.append(error)
            else:
                results.append(future.result())
        missing = len(events) - len(results)
        results += [TimeoutError(f"not published within {timeout} s")] * missing
        return results

    async def aclose(self) -> None:
        """Flush and close the connection; safe when ``open`` never ran or failed."""
        nc, self._nc, self._js = self._nc, None, None
        if nc is not None and not nc.is_closed:
            try:
                await asyncio.wait_for(nc.close(), timeout=2.0)
            except Exception as exc:  # noqa: BLE001 - closing: nothing left to do but log it
                if self._log_limit.allow("close"):
                    log.warning("nats_close_failed", sink=self.name, error=str(exc)[:200])
