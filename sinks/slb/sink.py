"""The SLB sink: detections and fused tracks as JC3IEDM object item reports over HTTPS.

Each event is POSTed on its own to ``{base_url}/object-items`` as the document of
``sinks.slb.jc3iedm`` with ``Idempotency-Key: <event_id>``, over TLS with a client
certificate and SLB's CA pinned (the hostname is always checked). One POST per event, up to
``max_in_flight`` at once, rather than a batch endpoint: every event keeps its own key and its
own answer, so a refusal names exactly the events refused and a retry re-sends only keys the
server de-duplicates.

The sink is stateless and holds no retry logic; its SinkRunner retries (and spools). The
answer decides, by the table every HTTPS sink shares (``gateway.transports.https``):

- 2xx: delivered; 409: SLB already has that key, so delivered too;
- a timeout, a lost connection, a TLS failure, 5xx, 429, 401/403 (our certificate not
  accepted yet), 408, 425 or a redirect (never followed): ``TransientSinkError`` naming the
  URL. A 429's or 503's ``Retry-After`` (at most ``max_retry_after_s``) is honoured: until it
  has passed, ``send`` raises ``TransientSinkError`` at once without contacting SLB;
- any other 4xx: the rest of the batch is delivered first, then ``PermanentSinkError`` with
  ``event_ids`` names the refused events and SLB's reason (at most 512 bytes).

Logs carry event ids, statuses and counts, never a document, a key or a password.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import anyio
import structlog
from pydantic import Field

from gateway.c2.sink import SinkConfig
from gateway.errors import PermanentSinkError
from gateway.events import Detection, Event, EventKind, Track
from gateway.transports.endpoint import HttpsEndpoint
from gateway.transports.httpspost import HttpsPoster, PostOutcome
from sinks.slb.jc3iedm import encode_object_item

__all__ = ["SlbSink", "SlbSinkConfig"]

log = structlog.get_logger(__name__)

#: The path below ``base_url`` that object item reports are POSTed to.
ITEMS_PATH = "/object-items"


class SlbSinkConfig(SinkConfig, HttpsEndpoint):
    """Options of the SLB sink: SLB's base URL, the TLS material and the kinds sent."""

    kinds: tuple[Literal["detection", "track"], ...] = Field(
        default=("detection", "track"),
        min_length=1,
        description="Event kinds reported: detection, track or both.",
    )
    max_in_flight: int = Field(
        default=4, ge=1, le=32, description="Reports POSTed at once (and pooled connections)."
    )
    max_retry_after_s: float = Field(
        default=60.0,
        ge=0,
        le=3600,
        description="Longest wait a 429's or 503's Retry-After can impose.",
    )


class SlbSink:
    """POSTs each detection or track to SLB as a JC3IEDM object item report."""

    config_model = SlbSinkConfig

    def __init__(self, name: str, config: SlbSinkConfig) -> None:
        self.name = name
        self.config = config
        self.url = config.url(ITEMS_PATH)
        self._kinds = frozenset(EventKind(kind) for kind in config.kinds)
        self._poster = HttpsPoster(
            name,
            self.url,
            config.tls_files,
            timeout_s=config.timeout_s,
            max_in_flight=config.max_in_flight,
            max_retry_after_s=config.max_retry_after_s,
        )
        #: ``anyio.current_time()`` before which SLB asked not to be contacted (Retry-After).
        self._hold_until = 0.0
        self.log = log.bind(sink=name, url=self.url)

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Detections and tracks, unless the config narrows it."""
        return self._kinds

    async def open(self) -> None:
        """Load the TLS material and make the client; connections open on the first POST.

        Raises ``TransientSinkError`` naming the file when the material cannot be loaded.
        """
        await self._poster.open()

    async def send(self, batch: Sequence[Event]) -> None:
        """POST every detection and track of ``batch`` (up to ``max_in_flight`` at once).

        Raises ``TransientSinkError`` if any POST should be retried, or while SLB's
        ``Retry-After`` runs (the whole batch is retried; SLB de-duplicates by key), else
        ``PermanentSinkError(event_ids=...)`` naming the events refused for good, after every
        other one was delivered.
        """
        items = [e for e in batch if isinstance(e, Detection | Track) and e.kind in self._kinds]
        if not items:
            return
        wait_s = self._hold_until - anyio.current_time()
        if wait_s > 0:
            raise self._poster.fail(
                f"{self.url}: holding back {wait_s:.1f} s more, as SLB asked (Retry-After)"
            )
        self._settle(await self._poster.post_all(items, encode_object_item), len(items))

    def _settle(self, outcomes: list[PostOutcome], total: int) -> None:
        delivered = sum(o.result in ("delivered", "duplicate") for o in outcomes)
        duplicates = sum(o.result == "duplicate" for o in outcomes)
        if delivered:
            self.log.info("slb_items_delivered", count=delivered, duplicates=duplicates)
        retry = [o for o in outcomes if o.result == "retry"]
        if retry:
            waits = [o.retry_after_s for o in retry if o.retry_after_s is not None]
            note = ""
            if waits:
                self._hold_until = anyio.current_time() + max(waits)
                note = f"; SLB asked for {max(waits):.1f} s (Retry-After)"
            raise self._poster.fail(
                f"{retry[0].detail} ({len(retry)} of {total} reports to retry, "
                f"{delivered} delivered{note})"
            )
        refused = [o for o in outcomes if o.result == "refused"]
        if refused:
            # One line per batch, not per report: a schema SLB no longer takes refuses them all.
            self.log.warning(
                "slb_items_refused",
                count=len(refused),
                event_ids=[o.event_id for o in refused[:5]],
                reason=refused[0].detail,
            )
            reasons = "; ".join(f"{o.event_id}: {o.detail}" for o in refused[:5])
            if len(refused) > 5:
                reasons += f"; and {len(refused) - 5} more"
            raise PermanentSinkError(
                f"sink {self.name}: {self.url} refused {len(refused)} of {total} reports: "
                + reasons,
                sink=self.name,
                event_ids=[o.event_id for o in refused],
                reasons={o.event_id: f"{self.url}: {o.detail}" for o in refused},
            )

    async def aclose(self) -> None:
        """Close the pooled connections; safe before ``open`` and after a failed one."""
        await self._poster.aclose()
