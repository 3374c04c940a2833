"""The health of one airframe's links: loss, last heard, up/down, and which one is active.

The active link is the preferred (lowest ``priority``) link heard within ``link_timeout_s``.
Failover is immediate when the active link times out; failback to a preferred link waits
until it has been up for ``failback_hold_s``, so a flapping link does not flap the airframe.
Every change of a link's (up, active) pair is published as a LinkState event.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import timedelta

from gateway.clock import Clock
from gateway.config import AirframeConfig
from gateway.events import BOOT_ID, Event, LinkState, event_id
from gateway.ops.instruments import Instruments

__all__ = ["AirframeLink", "LinkHealth"]


@dataclass(slots=True)
class AirframeLink:
    """How one airframe is heard on one link."""

    label: str
    priority: int
    received: int = 0
    lost: int = 0
    last_heard_mono: float | None = None
    up_since_mono: float | None = None
    is_up: bool = False
    is_active: bool = False
    latency_s: float | None = None
    published: tuple[bool, bool] | None = None
    last_seq: dict[int, int] = field(default_factory=dict)
    counted: int = 0
    """Frames of the autopilot component, the ones loss is measured on."""

    @property
    def loss_pct(self) -> float:
        """Autopilot frames lost to sequence gaps, as a percentage of those expected."""
        expected = self.counted + self.lost
        return 100.0 * self.lost / expected if expected else 0.0


class LinkHealth:
    """Tracks one airframe's links and elects the active one."""

    def __init__(
        self,
        config: AirframeConfig,
        publish: Callable[[Event], bool],
        clock: Clock,
        instruments: Instruments,
        *,
        on_active: Callable[[str | None], None] | None = None,
    ) -> None:
        self.config = config
        self._publish = publish
        self._clock = clock
        self._inst = instruments
        self._on_active = on_active
        self.links: dict[str, AirframeLink] = {
            link.label: AirframeLink(link.label, link.priority) for link in config.links
        }
        self.active: str | None = None
        self._seq = 0
        #: The component whose sequence numbers measure loss: MAV_COMP_ID_AUTOPILOT1 until a
        #: HEARTBEAT from a real autopilot says otherwise (``ingest`` sets it).
        self.autopilot_compid = 1

    def heard(self, label: str, compid: int, seq: int, now_mono: float) -> None:
        """Record one authenticated frame from component ``compid`` on link ``label``.

        Loss is measured on the autopilot component only (``autopilot_compid``): other
        components of a vehicle (a companion computer, a camera, a radio forwarding under the
        vehicle's sysid) often send constant or unrelated sequence numbers, and mixing them
        in made real, lossless logs read 70-80 % loss.
        """
        link = self.links.get(label)
        if link is None:
            return  # ingest attributes frames only on configured links; never add one here
        if compid == self.autopilot_compid:
            last = link.last_seq.get(compid)
            if last is not None:
                gap = (seq - last - 1) & 0xFF
                # 255 is the same sequence number again (a repeat, or reordering): not loss.
                if gap != 0xFF:
                    link.lost += gap
                    link.counted += 1
            else:
                link.counted += 1
            link.last_seq[compid] = seq
        link.received += 1
        link.last_heard_mono = now_mono
        if not link.is_up:
            link.is_up = True
            link.up_since_mono = now_mono
            self._elect(now_mono, f"heard on {label}")

    def latency(self, label: str, latency_s: float) -> None:
        """Record the latest one-way latency measured on link ``label`` (tunnel send time)."""
        link = self.links.get(label)
        if link is not None:
            link.latency_s = latency_s

    def check(self, now_mono: float) -> None:
        """Time out silent links, re-elect (failback waits out its hold), update metrics."""
        timeout = self.config.link_timeout_s
        reason = "hold elapsed"
        for link in self.links.values():
            heard = link.last_heard_mono
            if link.is_up and heard is not None and now_mono - heard > timeout:
                link.is_up = False
                link.up_since_mono = None
                reason = f"{link.label} not heard for {timeout} s"
        self._elect(now_mono, reason)
        for link in self.links.values():
            labels = (self.config.id, link.label)
            self._inst.link_up.labels(*labels).set(1.0 if link.is_up else 0.0)
            self._inst.link_loss.labels(*labels).set(link.loss_pct / 100.0)
            if link.last_heard_mono is not None:
                self._inst.link_last_heard_age.labels(*labels).set(now_mono - link.last_heard_mono)

    def _elect(self, now_mono: float, reason: str) -> None:
        current = self.links.get(self.active) if self.active else None
        hold = self.config.failback_hold_s
        candidates = [
            link
            for link in self.links.values()
            if link.is_up
            and (
                link is current
                or current is None
                or not current.is_up
                or (link.up_since_mono is not None and now_mono - link.up_since_mono >= hold)
            )
        ]
        best = min(candidates, key=lambda link: link.priority, default=None)
        if (
            current is not None
            and current.is_up
            and best is not None
            and best.priority >= current.priority
        ):
            best = current
        new_active = best.label if best else None
        if new_active != self.active:
            self.active = new_active
            if self._on_active is not None:
                self._on_active(new_active)
        now = self._clock()
        for link in self.links.values():
            link.is_active = link is best
            state = (link.is_up, link.is_active)
            if link.published == state or (link.published is None and not link.is_up):
                # Nothing changed, or a link never heard: its first state is "up" when heard.
                continue
            link.published = state
            self._seq += 1
            last_heard = (
                None
                if link.last_heard_mono is None
                else now - timedelta(seconds=max(0.0, now_mono - link.last_heard_mono))
            )
            self._publish(
                LinkState(
                    event_id=event_id(self.config.id, "link", BOOT_ID, self._seq),
                    airframe=self.config.id,
                    time=now,
                    link=link.label,
                    is_up=link.is_up,
                    is_active=link.is_active,
                    loss_pct=min(link.loss_pct, 100.0),
                    last_heard=last_heard,
                    reason=reason,
                )
            )

    def status(self) -> list[dict[str, object]]:
        """The links with their health, for /status."""
        now_mono = time.monotonic()
        return [
            {
                "link": link.label,
                "priority": link.priority,
                "up": link.is_up,
                "active": link.is_active,
                "loss_pct": round(link.loss_pct, 3),
                "frames": link.received,
                "latency_s": None if link.latency_s is None else round(link.latency_s, 4),
                "last_heard_age_s": None
                if link.last_heard_mono is None
                else round(now_mono - link.last_heard_mono, 3),
            }
            for link in self.links.values()
        ]
