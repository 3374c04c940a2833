"""SLB orders: the shipped schema and the parser agree, and every refusal names its field."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jsonschema import Draft202012Validator

from gateway.domain.geodesy import from_mgrs
from gateway.errors import OrderRejected
from gateway.events import OrderPriority, OrderTask
from sinks.slb.order import (
    EVENT_ID_PREFIX,
    SlbOrder,
    load_order_schema,
    order_id_of,
    parse_order_list,
    read_order,
    receipt_payload,
)

SCHEMA = load_order_schema()
ORDER = Draft202012Validator(SCHEMA, format_checker=Draft202012Validator.FORMAT_CHECKER)
RECEIPT = Draft202012Validator(
    {"$defs": SCHEMA["$defs"], "$ref": "#/$defs/receipt"},
    format_checker=Draft202012Validator.FORMAT_CHECKER,
)
LIST = Draft202012Validator(
    {"$defs": SCHEMA["$defs"], "$ref": "#/$defs/order_list"},
    format_checker=Draft202012Validator.FORMAT_CHECKER,
)
ORDER_DEF = SCHEMA["$defs"]["order"]

VALID: dict[str, Any] = {
    "order_id": "SLB-2026-0042",
    "issuer": "2 MekB S3",
    "issued": "2026-11-22T12:00:00Z",
    "airframe": "F26E-001",
    "task": "observe_point",
    "location": {"mgrs": "34W EU 31783 00413"},
    "not_before": "2026-11-22T12:05:00Z",
    "not_after": "2026-11-22T14:00:00+01:00",
    "target": "T-72 column on road 97",
    "track_id": None,
    "priority": "immediate",
    "reporting": "Report contact at once; SITREP every 15 min.",
    "control_measures": ["Stay east of phase line BLÅ", "Max 600 m MSL"],
}

times = st.datetimes(
    min_value=datetime(2000, 1, 1),  # noqa: DTZ001 - hypothesis takes naive bounds
    max_value=datetime(2100, 1, 1),  # noqa: DTZ001 - the zone comes from timezones=
    timezones=st.just(UTC),
).map(lambda t: t.isoformat().replace("+00:00", "Z"))
texts = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=30)
lat, lon = st.floats(-90, 90), st.floats(-180, 180)
corner = st.fixed_dictionaries({"lat_deg": lat, "lon_deg": lon})
points = st.fixed_dictionaries(
    {"lat_deg": lat, "lon_deg": lon}, optional={"alt_msl_m": st.floats(-500, 20_000)}
)
locations = st.one_of(
    points.map(lambda p: {"point": p}),
    st.just({"mgrs": "33VWG 12345 67890"}),
    st.lists(corner, min_size=3, max_size=64).map(lambda c: {"polygon": c}),
)
orders = st.fixed_dictionaries(
    {
        "order_id": st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9._:-]{0,40}\Z"),
        "issued": times,
        "task": st.sampled_from([t.value for t in OrderTask]),
        "location": locations,
    },
    optional={
        "issuer": st.none() | texts,
        "airframe": st.none() | texts,
        "target": st.none() | texts,
        "track_id": st.none() | texts,
        "priority": st.sampled_from([p.value for p in OrderPriority]),
        "reporting": st.none() | texts,
        "control_measures": st.lists(texts, max_size=16),
    },
)


def model_keys(model: Any) -> set[str]:
    return set(model.model_fields)


class TestSchemaAndParser:
    """The schema SLB is given and the parser the source runs are the same contract."""

    def test_is_valid_draft_2020_12(self) -> None:
        Draft202012Validator.check_schema(SCHEMA)
        ORDER.validate(VALID)

    def test_the_schemas_members_are_the_parsers_fields(self) -> None:
        assert set(ORDER_DEF["properties"]) == model_keys(SlbOrder)
        location = SlbOrder.model_fields["location"].annotation
        assert set(SCHEMA["$defs"]["location"]["properties"]) == model_keys(location)
        for name in ("order", "point", "corner", "location", "order_list", "receipt"):
            assert SCHEMA["$defs"][name]["additionalProperties"] is False, name
        assert set(ORDER_DEF["required"]) == {
            name for name, f in SlbOrder.model_fields.items() if f.is_required()
        }

    @settings(max_examples=150, deadline=None)
    @given(orders)
    def test_any_order_the_schema_accepts_is_read(self, order: dict[str, Any]) -> None:
        ORDER.validate(order)
        event = read_order(order, source="slb")
        assert event.event_id == EVENT_ID_PREFIX + order["order_id"]
        assert event.order_id == order["order_id"]
        assert event.task.value == order["task"]
        assert event.priority.value == order.get("priority", "routine")
        assert event.control_measures == tuple(order.get("control_measures", ()))
        if "polygon" in order["location"]:
            assert len(event.location.polygon) == len(order["location"]["polygon"])
        else:
            assert event.location.point is not None

    @pytest.mark.parametrize(
        ("change", "field"),
        [
            ({"issued": "2026-11-22T12:00:00"}, "issued"),  # no zone
            ({"issued": 1_795_000_000}, "issued"),
            ({"task": "fire_mission"}, "task"),
            ({"priority": "urgent"}, "priority"),
            ({"order_id": "a/b"}, "order_id"),
            ({"location": {"point": {"lat_deg": 95.0, "lon_deg": 18.0}}}, "location.point.lat_deg"),
            ({"location": {"point": {"lat_deg": "59", "lon_deg": 18.0}}}, "location.point.lat_deg"),
            ({"location": {"polygon": [{"lat_deg": 1, "lon_deg": 2}]}}, "location.polygon"),
            ({"location": {"mgrs": "33VWG 12345 67890", "point": {"lat_deg": 1, "lon_deg": 2}}},
             "location"),
            ({"location": {}}, "location"),
            ({"control_measures": ["x"] * 17}, "control_measures"),
            ({"airframe": "F" * 65}, "airframe"),
            ({"velocity": 3}, "velocity"),
        ],
    )  # fmt: skip
    def test_a_malformed_order_is_refused_by_both_naming_the_field(
        self, change: dict[str, Any], field: str
    ) -> None:
        order = {**VALID, **change}
        assert not ORDER.is_valid(order)
        with pytest.raises(OrderRejected) as refused:
            read_order(order, source="slb")
        assert str(refused.value).startswith(f"{field}: "), str(refused.value)

    def test_an_mgrs_reference_the_grid_cannot_decode_names_location_mgrs(self) -> None:
        order = {**VALID, "location": {"mgrs": "99ZZZ 12345 67890"}}
        with pytest.raises(OrderRejected, match=r"^location\.mgrs: "):
            read_order(order, source="slb")

    def test_a_reference_whose_square_is_not_in_its_band_is_refused(self) -> None:
        order = {**VALID, "location": {"mgrs": "34WEP1234567890"}}
        with pytest.raises(OrderRejected, match=r"^location\.mgrs: .*not in its band"):
            read_order(order, source="slb")

    def test_a_window_that_ends_before_it_starts_names_not_after(self) -> None:
        order = {**VALID, "not_before": "2026-11-22T13:00:00Z", "not_after": "2026-11-22T12:00:00Z"}
        with pytest.raises(OrderRejected, match=r"^not_after: "):
            read_order(order, source="slb")


class TestReading:
    """An order becomes the five lines of a FiveLineOrder."""

    def test_the_five_lines(self) -> None:
        event = read_order(VALID, source="brigade-slb")
        assert event.event_id == "slb-order-SLB-2026-0042"
        assert event.source == "brigade-slb"
        assert event.time == datetime(2026, 11, 22, 12, 0, tzinfo=UTC)
        assert event.task is OrderTask.OBSERVE_POINT
        ref = from_mgrs("34W EU 31783 00413")
        assert event.location.mgrs == "34W EU 31783 00413"
        assert event.location.point is not None
        assert (event.location.point.lat_deg, event.location.point.lon_deg) == (
            ref.lat_deg,
            ref.lon_deg,
        )
        assert event.not_after == datetime(2026, 11, 22, 13, 0, tzinfo=UTC)
        assert event.priority is OrderPriority.IMMEDIATE
        assert event.airframe == "F26E-001"
        assert event.control_measures == ("Stay east of phase line BLÅ", "Max 600 m MSL")

    def test_a_point_with_height_and_a_polygon(self) -> None:
        point = read_order(
            {**VALID, "location": {"point": {"lat_deg": 65.8, "lon_deg": 21.7, "alt_msl_m": 90}}},
            source="slb",
        )
        assert point.location.point is not None
        assert point.location.point.alt_msl_m == 90.0
        assert point.location.mgrs is None
        corners = [{"lat_deg": 65.8, "lon_deg": 21.6 + i / 100} for i in range(4)]
        area = read_order({**VALID, "location": {"polygon": corners}}, source="slb")
        lons = [c.lon_deg for c in area.location.polygon]
        assert lons == pytest.approx([21.6, 21.61, 21.62, 21.63])

    def test_order_ids(self) -> None:
        assert order_id_of(VALID) == "SLB-2026-0042"
        for bad in ({"order_id": "x\n"}, {"order_id": 7}, {}, ["order_id"], {"order_id": "é"}):
            assert order_id_of(bad) is None


class TestList:
    """The body of GET /orders: bounded, strict, never more than a ValueError."""

    def test_orders_beyond_the_limit_wait(self) -> None:
        body = json.dumps({"orders": [VALID] * 5}).encode()
        LIST.validate(json.loads(body))
        assert len(parse_order_list(body, max_orders=3)) == 3

    @pytest.mark.parametrize(
        "body",
        [
            b"",
            b"not json",
            b"[]",
            b'{"orders": {}}',
            b'{"orders": [], "more": 1}',
            b'{"orders": [NaN]}',
            b'{"orders": [' + b"9" * 5000 + b"]}",
            b"[" * 100_000 + b"]" * 100_000,
            b'{"orders": ["\xff"]}',
        ],
        ids=lambda b: repr(b[:24]),
    )
    def test_a_malformed_body_is_a_value_error(self, body: bytes) -> None:
        with pytest.raises(ValueError):  # noqa: PT011 - the message is checked elsewhere
            parse_order_list(body, max_orders=10)

    @pytest.mark.parametrize("depth", [100, 5000])
    def test_a_deeply_nested_order_is_refused(self, depth: int) -> None:
        """Beyond what the encoder can recurse into, too: never a RecursionError."""
        nested: list[Any] = []
        for _ in range(depth):
            nested = [nested]
        with pytest.raises(OrderRejected, match=r"^(order|target): "):
            read_order({**VALID, "target": nested}, source="slb")

    @settings(max_examples=200, deadline=None)
    @given(st.binary(max_size=200))
    def test_arbitrary_bytes_give_orders_or_a_value_error(self, body: bytes) -> None:
        try:
            elements = parse_order_list(body, max_orders=10)
        except ValueError:
            return
        for element in elements:
            reason = ""
            try:
                event = read_order(element, source="slb")
            except OrderRejected as exc:
                reason = str(exc)
            else:
                assert isinstance(element, dict)
                assert event.order_id == element["order_id"]
                continue
            assert ": " in reason  # names what is wrong


class TestReceipt:
    """Receipts are what the schema's $defs/receipt describes."""

    def test_received_and_rejected(self) -> None:
        t = datetime(2026, 11, 22, 12, 0, tzinfo=UTC)
        received = receipt_payload("A-1", "received", time=t, event_id="slb-order-A-1")
        RECEIPT.validate(received)
        assert received == {
            "order_id": "A-1",
            "status": "received",
            "reason": None,
            "event_id": "slb-order-A-1",
            "time": "2026-11-22T12:00:00.000Z",
            "seq": None,
        }
        executing = receipt_payload("A-1", "executing", time=t, event_id="e", seq=2)
        RECEIPT.validate(executing)
        assert executing["seq"] == 2
        rejected = receipt_payload("A-2", "rejected", time=t, reason="task: " + "x" * 900)
        RECEIPT.validate(rejected)
        assert len(rejected["reason"]) == 512
