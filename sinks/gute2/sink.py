"""The GUTE II sink: counter-UAS track handoffs to a battery, as JSON over HTTPS.

Each ``Handoff`` is POSTed to ``url`` as the document of ``sinks.gute2.codec`` with
``Idempotency-Key: <event_id>`` (the handoff id, with ``-r<n>`` for a revision), over TLS
with a client certificate and the battery's CA pinned (the hostname is always checked). A
handoff is a cue, never an order: the document always carries
``"operator_authorisation_required": true``, its schema allows nothing else, and nothing on
this path can command an effector; authorising an engagement stays with the battery's human
operator.

The sink holds no retry logic; its SinkRunner retries. The POSTs go through the client the
``slb`` sink also uses (``gateway.transports.httpspost``: one deadline for the whole exchange). The
answer decides:

- 2xx: delivered; 409: the battery already has that key, so delivered too;
- 401, 403 (our certificate not accepted yet), 408, 425, 429, 5xx, a redirect (never
  followed), a timeout, a lost connection or a TLS failure: ``TransientSinkError`` naming the
  URL; the idempotency key makes the retry safe;
- any other 4xx: the rest of the batch is delivered first, then ``PermanentSinkError`` with
  ``event_ids`` names the refused handoffs and the server's reason (at most 512 bytes).

Logs carry handoff ids, statuses and counts, never a document, a key or a password.
"""

from __future__ import annotations

from collections.abc import Sequence

import structlog
from pydantic import Field, field_validator

from gateway.c2.sink import SinkConfig
from gateway.errors import PermanentSinkError
from gateway.events import Event, EventKind, Handoff
from gateway.transports.endpoint import HttpsClientOptions, check_https_url
from gateway.transports.httpspost import HttpsPoster, PostOutcome
from sinks.gute2.codec import encode_handoff

__all__ = ["GuteSink", "GuteSinkConfig"]

log = structlog.get_logger(__name__)

_KINDS = frozenset({EventKind.HANDOFF})


class GuteSinkConfig(SinkConfig, HttpsClientOptions):
    """Options of the GUTE II sink: where the battery listens and the TLS material."""

    url: str = Field(description="https://HOST[:PORT]/PATH the handoffs are POSTed to.")
    max_in_flight: int = Field(
        default=4, ge=1, le=32, description="Handoffs POSTed at once (and pooled connections)."
    )

    @field_validator("url")
    @classmethod
    def _https_only(cls, value: str) -> str:
        return check_https_url(value, allow_query=True)


class GuteSink:
    """POSTs each handoff to one GUTE II battery; a cue for its operator, never an order."""

    config_model = GuteSinkConfig

    def __init__(self, name: str, config: GuteSinkConfig) -> None:
        self.name = name
        self.config = config
        self.url = config.url
        self._poster = HttpsPoster(
            name,
            config.url,
            config.tls_files,
            timeout_s=config.timeout_s,
            max_in_flight=config.max_in_flight,
        )
        self.log = log.bind(sink=name, url=config.url)

    @property
    def kinds(self) -> frozenset[EventKind]:
        """Handoffs only."""
        return _KINDS

    async def open(self) -> None:
        """Load the TLS material and make the client; connections open on the first POST.

        Raises ``TransientSinkError`` naming the file when the material cannot be loaded.
        """
        await self._poster.open()

    async def send(self, batch: Sequence[Event]) -> None:
        """POST every handoff of ``batch`` (up to ``max_in_flight`` at once).

        Raises ``TransientSinkError`` if any POST should be retried (the whole batch is; the
        battery de-duplicates by key), else ``PermanentSinkError(event_ids=...)`` naming the
        handoffs refused for good, after every other one was delivered.
        """
        handoffs = [event for event in batch if isinstance(event, Handoff)]
        if handoffs:
            # Retry-After is not read here: the runner's backoff paces the retry of a cue.
            self._settle(await self._poster.post_all(handoffs, encode_handoff), len(handoffs))

    def _settle(self, outcomes: list[PostOutcome], total: int) -> None:
        delivered = sum(o.result in ("delivered", "duplicate") for o in outcomes)
        duplicates = sum(o.result == "duplicate" for o in outcomes)
        if delivered:
            self.log.info("gute_handoffs_delivered", count=delivered, duplicates=duplicates)
        transient = [o for o in outcomes if o.result == "retry"]
        if transient:
            first = transient[0]
            raise self._poster.fail(
                f"{first.detail} ({len(transient)} of {total} handoffs to retry, "
                f"{delivered} delivered)"
            )
        refused = [o for o in outcomes if o.result == "refused"]
        if refused:
            for outcome in refused:
                self.log.warning(
                    "gute_handoff_refused", handoff_id=outcome.event_id, reason=outcome.detail
                )
            raise PermanentSinkError(
                f"sink {self.name}: {self.url} refused {len(refused)} of {total} handoffs: "
                + "; ".join(f"{o.event_id}: {o.detail}" for o in refused),
                sink=self.name,
                event_ids=[o.event_id for o in refused],
            )

    async def aclose(self) -> None:
        """Close the pooled connections; safe before ``open`` and after a failed one."""
        await self._poster.aclose()
