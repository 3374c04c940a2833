"""The simulated autopilot's mission protocol: uploads, downloads, and hostile ground stations.

Every message goes through the wire (packed by a pymavlink ground station, parsed as the
airframe parses it), so source ids and field types are what a real uplink gives.
"""

from __future__ import annotations

import math
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mav

from gateway.sim.mission import MissionServer, SimItem

GCS = (255, 191)


class Host:
    """The autopilot's side: records replaced missions and current items."""

    def __init__(self) -> None:
        self.replaced: list[tuple[SimItem, ...]] = []
        self.current = 0
        self._mav = mav.MAVLink(None, srcSystem=1, srcComponent=1)

    def mission_replaced(self, items: tuple[SimItem, ...]) -> None:
        self.replaced.append(items)
        self.current = 0

    def set_current(self, seq: int) -> bool:
        if self.replaced and 0 <= seq < len(self.replaced[-1]):
            self.current = seq
            return True
        return False

    def mission_current(self) -> Any:
        return self._mav.mission_current_encode(self.current)


class Station:
    """A ground station: builds messages and puts them through the wire to the server."""

    def __init__(self, server: MissionServer, sysid: int = GCS[0], compid: int = GCS[1]) -> None:
        self.server = server
        self.mav = mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.parser = mav.MAVLink(None)
        self.now = 0.0

    def send(self, name: str, *args: Any) -> list[Any]:
        msg = getattr(self.mav, f"{name}_encode")(*args)
        (parsed,) = self.parser.parse_buffer(bytes(msg.pack(self.mav)))
        return self.server.handle(parsed, self.now)

    def count(self, n: int, mission_type: int = 0) -> list[Any]:
        return self.send("mission_count", 1, 1, n, mission_type)

    def item(
        self,
        seq: int,
        *,
        command: int = 16,
        frame: int = 0,
        params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
        lat: float = 65.85,
        lon: float = 21.7,
        alt: float = 300.0,
        mission_type: int = 0,
    ) -> list[Any]:
        return self.send(
            "mission_item_int", 1, 1, seq, frame, command, 0, 1, *params,
            round(lat * 1e7), round(lon * 1e7), alt, mission_type,
        )  # fmt: skip

    def upload(self, n: int) -> list[Any]:
        replies = self.count(n)
        for seq in range(n):
            replies = self.item(seq, lat=65.85 + seq * 0.01)
        return replies


def server(**kwargs: Any) -> tuple[MissionServer, Host, Station]:
    host = Host()
    srv = MissionServer(1, host, mav.MAVLink(None, srcSystem=1, srcComponent=1), **kwargs)
    return srv, host, Station(srv)


def kinds(replies: list[Any]) -> list[tuple[str, int]]:
    """(type, seq) of requests, (type, result) of ACKs."""
    out = []
    for r in replies:
        t = r.get_type()
        out.append((t, int(r.type) if t == "MISSION_ACK" else int(getattr(r, "seq", -1))))
    return out


ACK = "MISSION_ACK"
REQ = "MISSION_REQUEST_INT"


class TestUpload:
    """MISSION_COUNT → MISSION_REQUEST_INT per item → MISSION_ACK, as PX4 and ArduPilot."""

    def test_each_item_is_asked_for_in_turn_and_the_mission_replaced_whole(self) -> None:
        _srv, host, gcs = server()
        assert kinds(gcs.count(3)) == [(REQ, 0)]
        assert kinds(gcs.item(0)) == [(REQ, 1)]
        assert kinds(gcs.item(1)) == [(REQ, 2)]
        assert host.replaced == []  # nothing changes before the whole mission is in
        replies = gcs.item(2, command=19, params=(30.0, 0.0, -200.0, 0.0))
        assert kinds(replies)[0] == (ACK, mav.MAV_MISSION_ACCEPTED)
        assert replies[1].get_type() == "MISSION_CURRENT"
        (items,) = host.replaced
        assert [i.command for i in items] == [16, 16, 19]
        assert items[2].params == (30.0, 0.0, -200.0, 0.0)
        assert (items[0].lat_deg, items[0].lon_deg, items[0].alt_m) == (65.85, 21.7, 300.0)
        assert (replies[0].target_system, replies[0].target_component) == GCS

    def test_the_mission_downloads_as_it_was_uploaded(self) -> None:
        _srv, _, gcs = server()
        gcs.upload(2)
        (count,) = gcs.send("mission_request_list", 1, 1, 0)
        assert (count.get_type(), count.count) == ("MISSION_COUNT", 2)
        (item,) = gcs.send("mission_request_int", 1, 1, 1, 0)
        assert (item.get_type(), item.seq, item.x, item.y, item.z) == (
            "MISSION_ITEM_INT", 1, 658_600_000, 217_000_000, 300.0,
        )  # fmt: skip
        (old,) = gcs.send("mission_request", 1, 1, 0, 0)
        assert old.get_type() == "MISSION_ITEM"
        assert math.isclose(old.x, 65.85, abs_tol=1e-5)
        assert kinds(gcs.send("mission_request_int", 1, 1, 2, 0)) == [
            (ACK, mav.MAV_MISSION_INVALID_SEQUENCE)
        ]

    def test_bogus_counts_are_refused_and_zero_clears(self) -> None:
        srv, host, gcs = server(max_items=50)
        gcs.upload(2)
        assert kinds(gcs.count(51)) == [(ACK, mav.MAV_MISSION_NO_SPACE)]
        assert kinds(gcs.count(65535)) == [(ACK, mav.MAV_MISSION_NO_SPACE)]
        assert len(srv.items) == 2  # the mission flown is untouched
        assert kinds(gcs.count(3, mission_type=1)) == [(ACK, mav.MAV_MISSION_UNSUPPORTED)]
        assert kinds(gcs.count(0)) == [(ACK, mav.MAV_MISSION_ACCEPTED)]
        assert srv.items == ()
        assert host.replaced[-1] == ()

    def test_a_sequence_out_of_order_is_refused_and_the_upload_goes_on(self) -> None:
        srv, _, gcs = server()
        gcs.count(3)
        assert kinds(gcs.item(2)) == [(ACK, mav.MAV_MISSION_INVALID_SEQUENCE)]
        assert kinds(gcs.item(9999)) == [(ACK, mav.MAV_MISSION_INVALID_SEQUENCE)]
        assert kinds(gcs.item(0)) == [(REQ, 1)]
        assert gcs.item(0) == []  # a duplicate: ignored, item 1 is still what is asked
        gcs.item(1)
        assert kinds(gcs.item(2))[0] == (ACK, mav.MAV_MISSION_ACCEPTED)
        assert len(srv.items) == 3

    def test_an_item_it_cannot_fly_ends_the_upload_and_keeps_the_old_mission(self) -> None:
        cases: list[tuple[dict[str, Any], int]] = [
            ({"command": 183}, mav.MAV_MISSION_UNSUPPORTED),  # DO_SET_SERVO: an effector
            ({"command": 211}, mav.MAV_MISSION_UNSUPPORTED),  # DO_GRIPPER
            ({"command": 4242}, mav.MAV_MISSION_UNSUPPORTED),
            ({"frame": 10}, mav.MAV_MISSION_UNSUPPORTED_FRAME),  # terrain: no DEM aboard
            ({"frame": 2}, mav.MAV_MISSION_UNSUPPORTED_FRAME),  # a waypoint needs a place
            ({"lat": 91.0}, mav.MAV_MISSION_INVALID_PARAM5_X),
            ({"lat": 89.5}, mav.MAV_MISSION_INVALID_PARAM5_X),  # no flying over a pole
            ({"lat": 0.0, "lon": 0.0}, mav.MAV_MISSION_INVALID_PARAM5_X),
            ({"lon": 181.0}, mav.MAV_MISSION_INVALID_PARAM6_Y),
            ({"alt": math.nan}, mav.MAV_MISSION_INVALID_PARAM7),
            ({"alt": 1e9}, mav.MAV_MISSION_INVALID_PARAM7),
            ({"command": 19, "params": (-5.0, 0, 0, 0)}, mav.MAV_MISSION_INVALID_PARAM1),
            ({"command": 19, "params": (math.inf, 0, 0, 0)}, mav.MAV_MISSION_INVALID_PARAM1),
            ({"command": 18, "params": (0.0, 0, 0, 0)}, mav.MAV_MISSION_INVALID_PARAM1),
            ({"command": 17, "params": (0, 0, 1e6, 0)}, mav.MAV_MISSION_INVALID_PARAM3),
            ({"params": (0, -3.0, 0, 0)}, mav.MAV_MISSION_INVALID_PARAM2),
            (
                {"command": 178, "frame": 2, "params": (0, 1e4, 0, 0)},
                mav.MAV_MISSION_INVALID_PARAM2,
            ),
        ]
        for fields, result in cases:
            srv, host, gcs = server()
            gcs.upload(1)
            gcs.count(2)
            gcs.item(0)
            assert kinds(gcs.item(1, **fields)) == [(ACK, result)], fields
            assert not srv.is_receiving
            assert len(srv.items) == 1
            assert len(host.replaced) == 1
            assert gcs.item(1) == []  # the upload is over: a late item is nothing

    def test_a_wrong_mission_type_is_unsupported(self) -> None:
        _srv, _, gcs = server()
        gcs.count(2)
        assert kinds(gcs.item(0, mission_type=1)) == [(ACK, mav.MAV_MISSION_UNSUPPORTED)]
        assert kinds(gcs.item(0)) == [(REQ, 1)]

    def test_a_silent_station_is_asked_again_then_cancelled(self) -> None:
        srv, _, gcs = server(item_timeout_s=0.5, item_retries=2)
        gcs.count(2)
        assert srv.poll(0.4) == []
        assert kinds(srv.poll(0.5)) == [(REQ, 0)]
        assert kinds(srv.poll(1.0)) == [(REQ, 0)]
        assert kinds(srv.poll(1.5)) == [(ACK, mav.MAV_MISSION_OPERATION_CANCELLED)]
        assert srv.next_deadline_s() == math.inf
        assert srv.poll(9.0) == []

    def test_an_item_answered_resets_the_retries(self) -> None:
        srv, _, gcs = server(item_timeout_s=0.5, item_retries=1)
        gcs.count(3)
        assert kinds(srv.poll(0.5)) == [(REQ, 0)]
        gcs.now = 0.7
        gcs.item(0)
        assert srv.next_deadline_s() == 1.2
        assert kinds(srv.poll(1.2)) == [(REQ, 1)]
        assert kinds(srv.poll(1.7)) == [(ACK, mav.MAV_MISSION_OPERATION_CANCELLED)]

    def test_a_second_station_is_denied_while_one_uploads(self) -> None:
        srv, _, gcs = server()
        other = Station(srv, sysid=254, compid=190)
        gcs.count(2)
        assert kinds(other.count(1)) == [(ACK, mav.MAV_MISSION_DENIED)]
        assert kinds(other.item(0)) == [(ACK, mav.MAV_MISSION_DENIED)]
        gcs.item(0)
        assert kinds(gcs.item(1))[0] == (ACK, mav.MAV_MISSION_ACCEPTED)

    def test_the_last_item_again_gets_the_lost_ack_again(self) -> None:
        srv, host, gcs = server()
        gcs.upload(2)
        assert kinds(gcs.item(1)) == [(ACK, mav.MAV_MISSION_ACCEPTED)]
        assert len(host.replaced) == 1
        assert srv.accepted == 1
        assert gcs.item(0) == []

    def test_the_same_station_counting_again_starts_over(self) -> None:
        srv, _, gcs = server()
        gcs.count(3)
        gcs.item(0)
        assert kinds(gcs.count(2)) == [(REQ, 0)]
        gcs.item(0)
        assert kinds(gcs.item(1))[0] == (ACK, mav.MAV_MISSION_ACCEPTED)
        assert len(srv.items) == 2


class TestOthers:
    """Clearing, the current item, and messages that are not for this airframe."""

    def test_clear_all_ends_an_upload_and_empties_the_mission(self) -> None:
        srv, _host, gcs = server()
        gcs.upload(2)
        gcs.count(3)
        assert kinds(gcs.send("mission_clear_all", 1, 1, 0)) == [(ACK, mav.MAV_MISSION_ACCEPTED)]
        assert srv.items == ()
        assert not srv.is_receiving
        assert kinds(gcs.send("mission_clear_all", 1, 1, 1)) == [(ACK, mav.MAV_MISSION_UNSUPPORTED)]

    def test_set_current_is_answered_with_mission_current(self) -> None:
        _srv, _host, gcs = server()
        gcs.upload(3)
        (current,) = gcs.send("mission_set_current", 1, 1, 2)
        assert (current.get_type(), current.seq) == ("MISSION_CURRENT", 2)
        (current,) = gcs.send("mission_set_current", 1, 1, 7)
        assert current.seq == 2  # out of range: unchanged

    def test_messages_for_another_system_or_component_get_nothing(self) -> None:
        srv, _, gcs = server()
        assert gcs.send("mission_count", 2, 1, 3, 0) == []
        assert gcs.send("mission_count", 1, 154, 3, 0) == []
        assert gcs.send("mission_request_list", 0, 0, 0) == []
        assert not srv.is_receiving


OPS = st.one_of(
    st.tuples(st.just("count"), st.integers(0, 65535), st.sampled_from([0, 0, 0, 1, 2, 255])),
    st.tuples(st.just("item"), st.integers(0, 65535), st.sampled_from([16, 19, 183, 300])),
    st.tuples(st.just("request"), st.integers(0, 65535), st.just(0)),
    st.tuples(st.just("clear"), st.just(0), st.sampled_from([0, 1])),
    st.tuples(st.just("tick"), st.integers(0, 10), st.just(0)),
)


@settings(max_examples=150, deadline=None)
@given(st.lists(OPS, max_size=80), st.booleans())
def test_a_hostile_station_never_breaks_it_nor_grows_it(ops: list[Any], two: bool) -> None:
    """Any sequence of counts, items, requests and clears, from one or two stations: at most
    two answers each, never more than ``max_items`` held, never an exception."""
    srv, host, gcs = server(max_items=20)
    stations = [gcs, Station(srv, sysid=7, compid=7)] if two else [gcs]
    for i, (op, n, extra) in enumerate(ops):
        st_ = stations[i % len(stations)]
        st_.now = gcs.now
        if op == "count":
            replies = st_.count(n, extra)
        elif op == "item":
            replies = st_.item(n, command=extra)
        elif op == "request":
            replies = st_.send("mission_request_int", 1, 1, n, 0)
        elif op == "clear":
            replies = st_.send("mission_clear_all", 1, 1, extra)
        else:
            gcs.now += n * 0.2
            replies = srv.poll(gcs.now)
        assert len(replies) <= 2
        assert len(srv.items) <= 20
        assert all(r.get_type().startswith("MISSION_") for r in replies)
    assert all(len(items) <= 20 for items in host.replaced)
    assert all(i.command in (16, 19) for i in srv.items)  # nothing else was ever taken
