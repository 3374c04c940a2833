"""The fleet as the assembly builds it: its share of /status, and the uplink it owns."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest

from gateway.config import Config
from gateway.errors import LinkUnavailable
from gateway.events import Event
from gateway.fleet.fleet import Fleet
from gateway.ops.instruments import Instruments


def config(*airframes: tuple[str, int, str]) -> Config:
    """Airframes (id, sysid, link uri) on unsecured links, two on one link if the uri repeats."""
    return Config.model_validate(
        {
            "health": {"enabled": False},
            "airframes": [
                {"id": name, "sysid": sysid, "links": [{"uri": uri, "security": "unsecured"}]}
                for name, sysid, uri in airframes
            ],
        }
    )


@pytest.fixture
def published() -> list[Event]:
    return []


def fleet(
    cfg: Config, published: list[Event], *, commander: bool = False
) -> tuple[Fleet, Instruments]:
    inst = Instruments()

    def publish(event: Event) -> bool:
        published.append(event)
        return True

    return Fleet(
        cfg, publish, inst, lambda: datetime(2026, 11, 27, tzinfo=UTC), commander=commander
    ), inst


def test_one_link_per_uri_and_the_status_share_the_gateway_shows(published: list[Event]) -> None:
    built, _ = fleet(
        config(("A", 1, "udp://127.0.0.1:0"), ("B", 2, "udp://127.0.0.1:0")), published
    )
    assert len(built.links) == 1
    assert sorted(built.sessions) == ["A", "B"]
    status = built.status()
    assert list(status) == ["airframes", "links", "hop_schedules", "passthroughs", "unknown_sysids"]
    assert [a["airframe"] for a in status["airframes"]] == ["A", "B"]
    assert status["links"][0]["security"] == "unsecured"
    assert (status["hop_schedules"], status["passthroughs"], status["unknown_sysids"]) == (
        [],
        [],
        [],
    )
    assert built.linked_count() == (0, 2)
    assert not built.is_bound()  # nothing runs yet
    assert built.commander is None
    assert fleet(config(("A", 1, "udp://127.0.0.1:0")), published, commander=True)[0].commander


@pytest.mark.anyio
async def test_the_uplink_refuses_an_airframe_with_no_link_up_and_counts_it(
    published: list[Event],
) -> None:
    built, inst = fleet(config(("A", 1, "udp://127.0.0.1:0")), published)
    with pytest.raises(LinkUnavailable, match="no link of this airframe is up"):
        await built.send("A", b"\xfd")
    # A session's own traffic (acknowledgements, hop schedules, commands) takes the same path.
    with pytest.raises(LinkUnavailable):
        await built.sessions["A"].send(b"\xfd")
    assert inst.uplink_refused.labels("A", "no_link").value == 2
