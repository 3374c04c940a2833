"""The fleet's airframe commander as the assembly builds it for a tasking processor."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from gateway.app import Gateway
from gateway.config import Config
from gateway.domain.mission import MAV_CMD_NAV_WAYPOINT, MissionItem
from gateway.flow.tasking import AirframeCommander

built: list[Gateway] = []


@pytest.fixture(autouse=True)
def closed() -> Iterator[None]:
    """Gateways built here are never run: close what running would have closed."""
    yield
    while built:
        gw = built.pop()
        for runner in gw.processors.values():
            runner.close()
        gw.spool.close()


def gateway(processors: list[dict[str, object]]) -> Gateway:
    config = Config.model_validate(
        {
            "health": {"enabled": False},
            "airframes": [
                {
                    "id": "F26E-001",
                    "sysid": 1,
                    "links": [{"uri": "udp://127.0.0.1:0", "security": "unsecured"}],
                }
            ],
            "processors": processors,
        }
    )
    built.append(Gateway(config))
    return built[-1]


def test_only_a_node_with_a_tasking_processor_gets_a_commander() -> None:
    assert gateway([]).commander is None
    assert gateway([{"name": "fusion", "type": "fusion"}]).commander is None
    tasked = gateway([{"name": "orders", "type": "orders"}])
    assert isinstance(tasked.commander, AirframeCommander)
    assert tasked.commander.is_known("F26E-001")
    assert not tasked.commander.is_known("F26E-404")
    assert not tasked.commander.is_linked("F26E-001")  # nothing heard from it yet


@pytest.mark.anyio
async def test_an_airframe_without_a_link_is_an_outcome_not_an_error() -> None:
    commander = gateway([{"name": "orders", "type": "orders"}]).commander
    assert commander is not None
    item = MissionItem(MAV_CMD_NAV_WAYPOINT, 65.85, 21.1, 500.0)
    uploaded = await commander.upload_mission("F26E-001", [item], timeout_s=0.1, retries=0)
    assert (uploaded.ok, uploaded.attempts) == (False, 0)
    assert uploaded.detail.startswith("not sent: ")
    commanded = await commander.command("F26E-001", 176, (1.0, 4.0, 4.0), timeout_s=0.1, retries=0)
    assert not commanded.ok
    assert commanded.detail.startswith("command 176 not sent: ")
