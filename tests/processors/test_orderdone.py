"""When a running order is done (``processors._orderdone``): the airframe's word and its
position together, time on task at a final loiter."""

from __future__ import annotations

from gateway.domain.geodesy import destination
from gateway.domain.mission import Loiter, Waypoint
from processors._orderdone import Progress

POINT = (65.85, 21.10)
SURVEY = (Waypoint(65.84, 21.02, 500.0), Waypoint(65.86, 21.06, 500.0))
OBSERVE = (Waypoint(*POINT, 500.0), Loiter(*POINT, 500.0, 10.0, 300.0))


def test_the_last_item_reached_is_not_enough_without_the_airframe_there() -> None:
    progress = Progress(SURVEY, acceptance_m=50.0)
    assert progress.reach(1)
    progress.position(65.83, 21.00, 0.0)  # still at home
    assert not progress.done(0.0)
    assert progress.why_not(0.0).startswith("the airframe was ")
    progress.position(*destination(65.86, 21.06, 90.0, 40.0), 1.0)  # 40 m off: there
    assert progress.done(1.0)


def test_there_without_the_last_item_reached_is_not_done() -> None:
    progress = Progress(SURVEY, acceptance_m=50.0)
    progress.position(65.86, 21.06, 0.0)
    assert progress.reach(0)
    assert not progress.done(0.0)
    assert progress.why_not(0.0) == "the airframe reported item 0 of 1 reached"


def test_items_it_was_never_given_do_not_count() -> None:
    progress = Progress(SURVEY, acceptance_m=50.0)
    assert not progress.reach(2)
    assert not progress.reach(-1)
    assert not progress.reach(65535)
    assert progress.reached == -1


def test_a_final_loiter_needs_its_time_on_task_without_a_break() -> None:
    progress = Progress(OBSERVE, acceptance_m=50.0)
    assert progress.reach(1)
    on_circle = destination(*POINT, 0.0, 300.0)
    progress.position(*on_circle, 100.0)
    assert not progress.done(105.0)
    assert progress.on_task_left_s(105.0) == 5.0
    progress.position(*destination(*POINT, 0.0, 1000.0), 106.0)  # left the circle: start over
    progress.position(*on_circle, 107.0)
    assert not progress.done(116.0)
    assert progress.done(117.0)
