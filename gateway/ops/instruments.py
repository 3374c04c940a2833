"""Every metric family the gateway exports, declared once per gateway instance.

Components receive the ``Instruments`` and keep the labelled children they need, so the
hot path only adds to an attribute.
"""

from __future__ import annotations

from gateway.ops.metrics import Registry
from gateway.ops.procmetrics import register_process_metrics
from gateway.ops.version import package_version

__all__ = ["Instruments"]


class Instruments:
    """The gateway's metric families on one registry."""

    def __init__(self, registry: Registry | None = None) -> None:
        self.registry = registry or Registry()
        r = self.registry
        self.link_bytes = r.counter("fg_link_bytes_total", "Bytes read from a link.", ("link",))
        self.link_chunks = r.counter(
            "fg_link_chunks_total", "Datagrams or stream reads from a link.", ("link",)
        )
        self.link_frames = r.counter(
            "fg_link_frames_total",
            "MAVLink frames accepted from a link (attributed and authenticated).",
            ("link",),
        )
        self.link_ignored = r.counter(
            "fg_link_frames_ignored_total",
            "Good frames not used, by reason (unknown_sysid, unknown_msgid, duplicate, "
            "handler_error).",
            ("link", "reason"),
        )
        self.link_rejected = r.counter(
            "fg_link_frames_rejected_total",
            "Frames refused, by reason (malformed, truncated, oversize, auth, replay, "
            "foreign_link: a configured airframe's sysid or key on a link not configured for it).",
            ("link", "reason"),
        )
        self.link_loss = r.gauge(
            "fg_link_loss_ratio",
            "Autopilot-component frames lost to MAVLink sequence gaps over those expected, "
            "per airframe and link.",
            ("airframe", "link"),
        )
        self.link_last_heard_age = r.gauge(
            "fg_link_last_heard_age_seconds",
            "Seconds since the airframe was last heard on the link.",
            ("airframe", "link"),
        )
        self.link_up = r.gauge(
            "fg_link_up", "1 when the airframe is heard on the link.", ("airframe", "link")
        )
        self.events = r.counter(
            "fg_events_total", "Events published on the bus, by kind.", ("kind",)
        )
        self.sink_sent = r.counter(
            "fg_sink_events_sent_total", "Events a sink accepted.", ("sink",)
        )
        self.sink_failed = r.counter(
            "fg_sink_send_failures_total",
            "Failed send calls, by reason (transient, timeout, error, permanent).",
            ("sink", "reason"),
        )
        self.sink_dropped = r.counter(
            "fg_sink_events_dropped_total",
            "Events a sink will never get, by reason (overflow: the spool was full; rejected; "
            "error; expired: stale after an outage, kept in the dead letters).",
            ("sink", "reason"),
        )
        self.sink_superseded = r.counter(
            "fg_sink_events_superseded_total",
            "Latest-wins events replaced by a newer one before the sink took them.",
            ("sink",),
        )
        self.sink_rate_limited = r.counter(
            "fg_route_events_rate_limited_total",
            "Latest-wins events thinned by a route's max_rate_hz.",
            ("sink",),
        )
        self.sink_outcomes = r.counter(
            "fg_sink_outcomes_total",
            "A sink's own counts of what became of what it took, by outcome (the ra180 sink: "
            "sent, held_back, suppressed, superseded, dropped_full ...).",
            ("sink", "outcome"),
        )
        self.sink_queue = r.gauge(
            "fg_sink_queue_depth", "Events waiting for a sink, by class.", ("sink", "class")
        )
        self.sink_latency = r.histogram(
            "fg_sink_delivery_latency_seconds",
            "From ingest to the sink accepting the event.",
            ("sink",),
        )
        self.sink_open = r.gauge("fg_sink_open", "1 while a sink is open and healthy.", ("sink",))
        self.sink_circuit = r.gauge(
            "fg_sink_circuit_state",
            "A sink's circuit breaker: 0 closed, 1 half-open (probing), 2 open (failing).",
            ("sink",),
        )
        self.sink_late = r.counter(
            "fg_sink_events_late_total",
            "Durable events delivered after their kind's stale threshold, marked late_by_s.",
            ("sink", "kind"),
        )
        self.spool_bytes = r.gauge("fg_spool_bytes", "Bytes the spool holds (in-use pages).")
        self.spool_max_bytes = r.gauge("fg_spool_max_bytes", "The spool's size cap.")
        self.spool_pending = r.gauge(
            "fg_spool_pending_events", "Durable events owed to a sink, in the spool.", ("sink",)
        )
        self.spool_refused = r.counter(
            "fg_spool_refused_total", "Durable events refused because the spool was full."
        )
        self.spool_dead_letters = r.gauge("fg_spool_dead_letters", "Dead letters held.")
        self.spool_commits = r.counter(
            "fg_spool_commits_total",
            "Spool transactions committed (one per loop pass that wrote: a group commit).",
        )
        self.spool_commit_failures = r.counter(
            "fg_spool_commit_failures_total",
            "Spool writes that failed to commit (nothing of them acknowledged), by reason "
            "(full, io, readonly, busy, corrupt, other).",
            ("reason",),
        )
        self.spool_wal_lost_frames = r.gauge(
            "fg_spool_wal_lost_frames",
            "WAL frames of committed transactions SQLite could not replay at this start "
            "(a damaged -wal file; a copy is kept beside the spool).",
        )
        self.spool_wal_lost_commits = r.gauge(
            "fg_spool_wal_lost_commits",
            "Committed transactions among the WAL frames lost at this start.",
        )
        self.spool_integrity_failures = r.gauge(
            "fg_spool_integrity_failures",
            "Problems the integrity check found in the spool at this start (the damaged file "
            "was moved aside and the gateway started on an empty spool).",
        )
        self.detections_acked = r.counter(
            "fg_detections_acknowledged_total",
            "FISCHER_DETECTION_ACKs queued to airframes, by result (held, duplicate).",
            ("airframe", "result"),
        )
        self.uplink_frames = r.counter(
            "fg_uplink_sends_total",
            "Sends to an airframe (passthrough, commands), per airframe and link.",
            ("airframe", "link"),
        )
        self.uplink_refused = r.counter(
            "fg_uplink_refused_total",
            "Sends to an airframe refused, by reason (no_link, no_peer, unsignable, send_failed).",
            ("airframe", "reason"),
        )
        self.passthrough_refused = r.counter(
            "fg_passthrough_refused_total",
            "Ground-station frames the passthrough did not relay, by airframe and reason "
            "(docs/security.md#the-passthrough).",
            ("airframe", "reason"),
        )
        self.processor_events = r.counter(
            "fg_processor_events_total",
            "Events into and out of a processor, and dropped when its inbox was full.",
            ("processor", "direction"),
        )
        self.extension_refused = r.counter(
            "fg_extension_refused_total",
            "Extension events refused before the bus, by publisher and reason "
            "(undeclared: a type its processor does not declare; invalid: data its model rejects).",
            ("publisher", "reason"),
        )
        self.link_latency = r.histogram(
            "fg_link_latency_seconds",
            "Airframe to gateway, from the tunnel's send time (needs both clocks on GPS/NTP).",
            ("airframe", "link"),
        )
        self.build_info = r.gauge(
            "fg_build_info", "Always 1; the label is the running gateway's version.", ("version",)
        )
        self.build_info.labels(package_version()).set(1)
        self.ready = r.gauge(
            "fg_ready", "1 once every link is bound and every sink open (as /readyz), else 0."
        )
        self.dem_source_up = r.gauge(
            "fg_dem_source_up",
            "1 while a DEM source is used for AGL, 0 once disabled.",
            ("source",),
        )
        self.dem_errors = r.counter(
            "fg_dem_errors_total",
            "DEM tiles or sources that failed, by source and reason (unreadable, missing, ...).",
            ("source", "reason"),
        )
        self.hop_events = r.counter(
            "fg_hop_events_total",
            "FISCHER_HOP_EVENTs from an airframe, by reason (scheduled, jammed, interference); "
            "jammed counts the jam-triggered hops.",
            ("airframe", "reason"),
        )
        self.hops = r.counter(
            "fg_hops_total",
            "Hops the airframe's radio reported flying (from the hop counts of its events).",
            ("airframe",),
        )
        self.hop_events_dropped = r.counter(
            "fg_hop_events_dropped_total",
            "Hop events counted but not published: over the per-airframe rate cap.",
            ("airframe",),
        )
        self.hop_schedule_state = r.gauge(
            "fg_hop_schedule_state",
            "1 for the state of the airframe's hop-schedule upload (waiting_link, sent, "
            "accepted, refused, retrying, invalid), 0 for the others.",
            ("airframe", "state"),
        )
        self.hop_schedule_sends = r.counter(
            "fg_hop_schedule_sends_total",
            "FISCHER_HOP_SCHEDULE uploads sent to an airframe (re-sends included).",
            ("airframe",),
        )
        self.hop_schedule_answers = r.counter(
            "fg_hop_schedule_answers_total",
            "FISCHER_HOP_SCHEDULE_ACKs for the gateway's schedule, by result.",
            ("airframe", "result"),
        )
        register_process_metrics(r)
