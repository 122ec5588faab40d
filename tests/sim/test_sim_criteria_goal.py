"""The one goal rule (`yawil.sim.criteria.goal_reached`): metres of route left, whatever the waypoint spacing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from yawil.sim.criteria import (
    GOAL_RADIUS,
    GOAL_ROUTE_LEFT,
    GoalCriterion,
    goal_reached,
    route_left,
    route_left_table,
)
from yawil.sim.types import EventKind

FIVE_M = np.stack([np.arange(0.0, 101.0, 5.0), np.zeros(21)], axis=1)  # 21 waypoints 5 m apart, goal (100, 0)


def test_constants_are_the_protocol() -> None:
    assert (GOAL_RADIUS, GOAL_ROUTE_LEFT) == (2.0, 10.0)


def test_route_left_measures_metres_on_a_five_metre_route() -> None:
    assert route_left(FIVE_M, 0) == 100.0 and route_left(FIVE_M, 18) == 10.0 and route_left(FIVE_M, 20) == 0.0
    # At the goal itself, the projection 15 m back (3 waypoints) is not enough; 10 m back (2 waypoints) is.
    # The former waypoint window (10 waypoints) would have accepted index 10, 50 m of route still ahead.
    assert not goal_reached(100.0, 0.0, FIVE_M, 10)
    assert not goal_reached(100.0, 0.0, FIVE_M, 17)
    assert goal_reached(100.0, 0.0, FIVE_M, 18) and goal_reached(98.1, 0.0, FIVE_M, 20)
    assert not goal_reached(97.9, 0.0, FIVE_M, 20)  # 2.1 m from the goal


def test_goal_criterion_fires_once_by_metres_on_a_five_metre_route() -> None:
    g = GoalCriterion(FIVE_M)
    assert g.update(0.1, 100.0, 0.0, 10) == [] and g.update(0.2, 100.0, 0.0, 17) == []
    ev = g.update(0.3, 100.0, 0.0, 18)
    assert [e.kind for e in ev] == [EventKind.GOAL_REACHED] and g.reached
    assert g.update(0.4, 100.0, 0.0, 20) == []
    g.reset()
    assert len(g.update(0.5, 100.0, 0.0, 20)) == 1


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="route_xy"):
        route_left(np.zeros((3, 3)), 0)
    with pytest.raises(ValueError, match="route_xy"):
        GoalCriterion(np.zeros((0, 2)))
    with pytest.raises(ValueError, match="route index 21"):
        goal_reached(100.0, 0.0, FIVE_M, 21)
    with pytest.raises(ValueError, match="route index -1"):
        route_left(FIVE_M, -1)
    with pytest.raises(ValueError, match="left has 3 entries"):
        goal_reached(100.0, 0.0, FIVE_M, 20, left=np.zeros(3))


steps = st.lists(st.tuples(st.floats(0.2, 8.0), st.floats(-math.pi, math.pi)), min_size=1, max_size=40)


def _route(legs: list[tuple[float, float]]) -> np.ndarray:
    d = np.array([[length * math.cos(h), length * math.sin(h)] for length, h in legs])
    return np.concatenate([np.zeros((1, 2)), np.cumsum(d, axis=0)])


@settings(max_examples=150, deadline=None)
@given(legs=steps, data=st.data())
def test_rule_is_radius_and_metres_left_for_any_spacing(
    legs: list[tuple[float, float]], data: st.DataObject
) -> None:
    xy = _route(legs)
    index = data.draw(st.integers(0, len(xy) - 1))
    dist = data.draw(st.floats(0.0, 4.0))
    ang = data.draw(st.floats(-math.pi, math.pi))
    left = sum(length for length, _ in legs[index:])
    assume(abs(left - GOAL_ROUTE_LEFT) > 1e-9 and abs(dist - GOAL_RADIUS) > 1e-9)
    table = route_left_table(xy)
    assert table[index] == pytest.approx(left, abs=1e-9) and table[-1] == 0.0
    x, y = xy[-1, 0] + dist * math.cos(ang), xy[-1, 1] + dist * math.sin(ang)
    expected = dist < GOAL_RADIUS and left < GOAL_ROUTE_LEFT
    assert goal_reached(x, y, xy, index) is expected
    assert goal_reached(x, y, xy, index, left=table) is expected
    assert bool(GoalCriterion(xy).update(0.1, x, y, index)) is expected
