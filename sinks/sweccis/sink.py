"""The SWECCIS sink: detections, tracks and airframe telemetry as FAS documents over TLS.

Each event becomes the documents of ``sinks.sweccis.fas`` (docs/sweccis.md has the
table): a detection or a track one **Intel** document; telemetry a **Logistics** document
(health) at most ``logistics_max_rate_hz`` and an **Operations** document (position and
state, only with a position) at most ``operations_max_rate_hz`` per airframe, by the
telemetry's own time; telemetry arriving faster is delivered by being left out. The
connection (``sinks.sweccis.link``: TLS 1.2+, client certificate, pinned CA,
4-byte length frames) registers the FAS this sink's ``kinds`` need before anything is sent.

``send`` returns only once the server has acknowledged every document of the batch, so the
spool behind the SinkRunner removes only what is confirmed. The server's answer decides:

- ``accepted`` or ``duplicate`` (it already had that id): delivered;
- ``rejected``: the rest of the batch is acknowledged first, then ``PermanentSinkError``
  with ``event_ids`` names each event with a rejected document and the server's reason;
- no connection, no registration, no ack within ``timeout_s``, a connection lost: the link
  is closed and ``TransientSinkError`` names the endpoint; the runner retries the batch and
  the server answers ``duplicate`` for what it already had.

An event the schema cannot carry (a NaN, a name over 64 characters) is refused the same way
as a rejected one. The sink keeps no delivery state beyond the per-airframe time of the last
document of each telemetry FAS (at most ``MAX_AIRFRAMES``). Logs carry ids, counts and
reasons, never a document or a key.
"""

from __future__ import annotations

import ssl
from collections import Counter, OrderedDict
from collections.abc import Sequence
from datetime import datetime, timedelta

import anyio
import anyio.to_thread
import structlog
from pydantic import Field, field_validator

from gateway.c2.sink import SinkConfig
from gateway.errors import FrameError, LinkError, PermanentSinkError, TransientSinkError
from gateway.events import Event, EventKind, Telemetry
from gateway.ops.logsetup import RateLimit
from gateway.transports.tls import tls_context
from sinks.sweccis.fas import Ack, Document, Fas, encode_event
from sinks.sweccis.link import SweccisLink, SweccisLinkOptions

__all__ = ["MAX_AIRFRAMES", "SweccisSink", "SweccisSinkConfig"]

log = structlog.get_logger(__name__)

#: Airframes whose last telemetry document times are remembered (the oldest go first).
MAX_AIRFRAMES = 4096
_KINDS = frozenset({EventKind.DETECTION, EventKind.TRACK, EventKind.TELEMETRY})
_SUMMARY_INTERVAL_S = 60.0
_Timing = dict[str, tuple[tuple[str, Fas], datetime]]


class SweccisSinkConfig(SinkConfig, SweccisLinkOptions):
    """Options of the SWECCIS sink: the server, the TLS material, the kinds and the rates."""

    kinds: frozenset[EventKind] = Field(
        default=_KINDS,
        min_length=1,
        description="Kinds sent: detection and track (Intel), telemetry (Logistics, Operations).",
    )
    operations_max_rate_hz: float = Field(
        default=1.0, gt=0, le=10, description="Operations documents per airframe per second."
    )
    logistics_max_rate_hz: float = Field(
        default=0.2, gt=0, le=10, description="Logistics documents per airframe per second."
    )
    max_in_flight: int = Field(
        default=32, ge=1, le=1024, description="Documents awaiting their ack at once."
    )

    @field_validator("kinds")
    @classmethod
    def _known_kinds(cls, value: frozenset[EventKind]) -> frozenset[EventKind]:
        if not value <= _KINDS:
            extra = sorted(kind.value for kind in value - _KINDS)
            raise ValueError(f"SWECCIS carries detection, track and telemetry, not {extra}")
        return value


class SweccisSink:
    """Publishes events to one SWECCIS server and returns once each document is acknowledged."""

    config_model = SweccisSinkConfig

    def __init__(self, name: str, config: SweccisSinkConfig) -> None:
        self.name = name
        self.config = config
        self._link: SweccisLink | None = None
        self._context: ssl.SSLContext | None = None
        self._sent_at: OrderedDict[tuple[str, Fas], datetime] = OrderedDict()
        self._intervals = {
            Fas.OPERATIONS: timedelta(seconds=1.0 / config.operations_max_rate_hz),
            Fas.LOGISTICS: timedelta(seconds=1.0 / config.logistics_max_rate_hz),
        }
        fas: set[Fas] = set()
        if config.kinds & {EventKind.DETECTION, EventKind.TRACK}:
            fas.add(Fas.INTEL)
        if EventKind.TELEMETRY in config.kinds:
            fas |= {Fas.LOGISTICS, Fas.OPERATIONS}
        #: The FAS registered on every connection.
        self.publishes = frozenset(fas)
        #: Documents by outcome (accepted, duplicate, rejected, refused: not encodable,
        #: skipped: over the rate) and frames skipped on the link (invalid, unexpected, stray).
        self.counts: Counter[str] = Counter()
        self._log_limit = RateLimit(interval_s=10.0)
        self._summary_limit = RateLimit(interval_s=_SUMMARY_INTERVAL_S)
        self.log = log.bind(sink=name, uri=config.uri)

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Detections, tracks and telemetry, unless the config narrows them."""
        return self.config.kinds

    def _fail(self, what: str) -> TransientSinkError:
        return TransientSinkError(f"sink {self.name}: {what}", sink=self.name)

    async def open(self) -> None:
        """Connect and register; ``TransientSinkError`` naming the endpoint and why if not."""
        if self._link is not None:
            return
        if self._context is None:
            try:
                self._context = await anyio.to_thread.run_sync(tls_context, self.config.tls_files)
            except (OSError, ValueError, ssl.SSLError) as exc:
                raise self._fail(f"{self.config.uri}: TLS material unusable: {exc}") from exc
        try:
            self._link = await SweccisLink.connect(
                self.config, self._context, publish=self.publishes
            )
        except LinkError as exc:
            raise self._fail(str(exc)) from exc
        self.log.info("sweccis_registered", publishes=sorted(f.value for f in self.publishes))

    async def send(self, batch: Sequence[Event]) -> None:
        """Publish ``batch`` and return once every document is acknowledged (module docstring)."""
        documents, refused, timing = self._encode(batch)
        acks: dict[str, Ack] = {}
        if documents:
            acks = await self._exchange(documents)
        rejected: dict[str, str] = dict(refused)
        delivered = 0
        for document in documents:
            ack = acks[document.doc_id]
            self.counts[ack.status] += 1
            if ack.status == "rejected":
                reason = f"{document.fas} {document.doc_id} rejected: {ack.reason or '?'}"
                rejected.setdefault(document.event_id, reason)
                if self._log_limit.allow("rejected"):
                    self.log.warning(
                        "sweccis_document_rejected", doc_id=document.doc_id, reason=ack.reason
                    )
            else:
                delivered += 1
                if document.doc_id in timing:
                    self._remember(*timing[document.doc_id])
        if delivered and self._summary_limit.allow("delivered"):
            self.log.info("sweccis_documents_delivered", **dict(self.counts))
        if rejected:
            raise PermanentSinkError(
                f"sink {self.name}: {self.config.uri} refused {len(rejected)} events: "
                + "; ".join(rejected.values()),
                sink=self.name,
                event_ids=rejected,
                reasons=rejected,
            )

    def _encode(self, batch: Sequence[Event]) -> tuple[list[Document], dict[str, str], _Timing]:
        """The batch's documents (each id once), the events refused and why, and for each
        telemetry document the airframe and time to remember once it is acknowledged."""
        documents: dict[str, Document] = {}
        refused: dict[str, str] = {}
        planned: dict[tuple[str, Fas], datetime] = {}
        timing: _Timing = {}
        for event in batch:
            if event.kind not in self.config.kinds:
                continue
            logistics = operations = True
            if isinstance(event, Telemetry):
                logistics = self._is_due(event, Fas.LOGISTICS, planned)
                operations = self._is_due(event, Fas.OPERATIONS, planned)
            try:
                encoded = encode_event(
                    event,
                    logistics=logistics,
                    operations=operations,
                    version=str(self.config.fas_version),
                )
                for document in encoded:
                    if len(document.payload) > self.config.max_frame_bytes:
                        raise ValueError(
                            f"{document.fas} {document.doc_id}: {len(document.payload)} bytes, "
                            f"more than max_frame_bytes {self.config.max_frame_bytes}"
                        )
            except ValueError as exc:
                refused[event.event_id] = str(exc)
                self.counts["refused"] += 1
                if self._log_limit.allow("refused"):
                    self.log.warning(
                        "sweccis_event_refused", event_id=event.event_id, reason=str(exc)
                    )
                continue
            for document in encoded:
                documents.setdefault(document.doc_id, document)  # an event twice: sent once
                if isinstance(event, Telemetry):
                    timing[document.doc_id] = ((event.airframe, document.fas), event.time)
        return list(documents.values()), refused, timing

    def _is_due(
        self, telemetry: Telemetry, fas: Fas, planned: dict[tuple[str, Fas], datetime]
    ) -> bool:
        key = (telemetry.airframe, fas)
        last = planned.get(key) or self._sent_at.get(key)
        # A time before the last one (an airframe clock reset) restarts the spacing.
        if last is not None and last <= telemetry.time < last + self._intervals[fas]:
            self.counts["skipped"] += 1
            return False
        planned[key] = telemetry.time
        return True

    def _remember(self, key: tuple[str, Fas], when: datetime) -> None:
        self._sent_at[key] = when
        self._sent_at.move_to_end(key)
        while len(self._sent_at) > MAX_AIRFRAMES * 2:  # two telemetry FAS per airframe
            self._sent_at.popitem(last=False)

    async def _exchange(self, documents: list[Document]) -> dict[str, Ack]:
        # A connection idle since the last batch may have been closed by the server: when
        # that is what the first attempt finds, one fresh connection is tried at once.
        retried = False
        while True:
            was_open = self._link is not None
            await self.open()
            link = self._link
            assert link is not None  # noqa: S101 - open() made it or raised
            try:
                return await link.exchange(documents, window=self.config.max_in_flight)
            except LinkError as exc:
                await self._drop()
                if was_open and not retried:
                    retried = True
                    self.log.info("sweccis_reconnecting", reason=str(exc))
                    continue
                raise self._fail(str(exc)) from exc
            except FrameError as exc:
                await self._drop()
                raise self._fail(f"{self.config.uri}: {exc}") from exc
            except TimeoutError:
                await self._drop()
                raise self._fail(
                    f"{self.config.uri}: no acknowledgement within {self.config.timeout_s} s"
                ) from None
            except BaseException:
                await self._drop()  # cancelled mid-batch: half a frame may be on the wire
                raise
            finally:
                self.counts.update(link.counts)
                link.counts.clear()

    async def _drop(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            with anyio.CancelScope(shield=True):
                await link.aclose()

    async def aclose(self) -> None:
        """Close the connection; safe before ``open`` and after a failed one."""
        await self._drop()
