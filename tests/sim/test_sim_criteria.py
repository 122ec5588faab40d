"""One test per criterion (backend-neutral inputs), plus the embedded world producing each event."""

from __future__ import annotations

import math

import numpy as np
import pytest

from yawil.sim import Control, Event, EventKind, Pose, Scenario
from yawil.sim.criteria import (
    BoxContacts,
    CollisionCriterion,
    DistanceDrivenCriterion,
    GoalCriterion,
    LaneInvasionCriterion,
    RedLightCriterion,
    RouteProgressCriterion,
    TimeoutCriterion,
    boxes_overlap,
)
from yawil.sim.town.map.town import get_town
from yawil.sim.town.traffic.lights import GREEN, RED, TrafficLights
from yawil.sim.town.world import EmbeddedWorld


def test_boxes_overlap_is_oriented() -> None:
    ego = (0.0, 0.0, 0.0, 4.0, 2.0)
    boxes = np.array([[3.9, 0.0, 0.0, 4.0, 2.0], [4.1, 0.0, 0.0, 4.0, 2.0], [2.0, 2.2, math.pi / 4, 1.0, 1.0],
                      [2.0, 1.6, math.pi / 4, 1.0, 1.0]])
    assert boxes_overlap(ego, boxes).tolist() == [True, False, False, True]


def test_collision_counted_once_per_contact_with_ids() -> None:
    c = CollisionCriterion()
    ego = (0.0, 0.0, 0.0, 4.0, 2.0)
    boxes = np.array([[3.0, 0.0, 0.0, 4.0, 2.0], [0.0, 1.2, 0.0, 0.6, 0.6]])
    both = BoxContacts(ego, boxes, np.array([7, 3]), ["vehicle", "static"])
    ev = c.update(0.1, 0.0, 0.0, both)
    assert {(e.other_type, e.other_id) for e in ev} == {("vehicle", 7), ("static", None)}
    assert c.update(0.2, 0.0, 0.0, both) == []
    assert c.update(0.3, 0.0, 0.0, BoxContacts(ego, boxes[:0], np.zeros(0, dtype=np.int64), [])) == []
    assert len(c.update(0.4, 0.0, 0.0, BoxContacts(ego, boxes[:1], np.array([7]), ["vehicle"]))) == 1  # a new contact


def test_lane_invasion_once_per_entry() -> None:
    c = LaneInvasionCriterion()
    seq = ["lane", "opposite_lane", "opposite_lane", "lane", "opposite_lane", "junction", "off_road", "off_road"]
    events = [e.detail for k, r in enumerate(seq) for e in c.update(k * 0.1, 0.0, 0.0, r)]
    assert events == ["opposite_lane", "opposite_lane", "off_road"]
    with pytest.raises(ValueError, match="region"):
        c.update(1.0, 0, 0, "sky")


def test_red_light_crossing_and_light_passed() -> None:
    c = RedLightCriterion(np.array([4]), np.array([[0.0, 0.0]]), np.array([[0.0, -3.5]]), np.array([0.0]))
    assert c.update(0.1, (-1.0, -1.75), (-0.5, -1.75), 0.0, ["red"]) == []  # not there yet
    ev = c.update(0.2, (-0.5, -1.75), (0.3, -1.75), 0.0, ["red"])
    assert [e.kind for e in ev] == [EventKind.LIGHT_PASSED, EventKind.RED_LIGHT] and ev[0].other_id == 4
    ev = c.update(0.3, (-0.5, -1.75), (0.3, -1.75), 0.0, ["green"])
    assert [e.kind for e in ev] == [EventKind.LIGHT_PASSED]
    assert c.update(0.4, (0.3, -1.75), (-0.5, -1.75), math.pi, ["red"]) == []  # other direction
    assert c.update(0.5, (-0.5, 2.0), (0.3, 2.0), 0.0, ["red"]) == []  # beside the line (opposite lane)


def test_progress_distance_goal_timeout() -> None:
    route = np.stack([np.arange(0.0, 50.0), np.zeros(50)], axis=1)
    p = RouteProgressCriterion(route)
    assert p.update(10.2, 0.5) == 10 and p.progress == pytest.approx(10.0)
    p.update(3.0, 0.0)
    assert p.index == 5 and p.progress == pytest.approx(10.0)  # searched near the last index, progress kept
    d = DistanceDrivenCriterion()
    d.update((0, 0), (3, 4))
    assert d.update((3, 4), (3, 5)) == pytest.approx(6.0)
    g = GoalCriterion(route)
    assert g.update(1.0, 45.0, 0.0, 45) == [] and len(g.update(1.1, 47.5, 0.5, 47)) == 1
    assert g.update(1.2, 49, 0, 49) == []  # once
    ang = np.linspace(0.0, 2 * np.pi, 401)
    loop_xy = np.stack([30.0 * np.sin(ang), 30.0 * (1.0 - np.cos(ang)) + 0.5], axis=1)  # goal next to its start
    loop = GoalCriterion(loop_xy)
    assert loop.update(0.1, 0.0, 0.5, 1) == [] and loop.update(0.2, 0.0, 0.5, 200) == []
    assert len(loop.update(9.0, 0.0, 0.5, 395)) == 1
    t = TimeoutCriterion(2.0)
    assert t.update(1.9, 0, 0) == [] and t.update(2.0, 0, 0)[0].kind is EventKind.TIMEOUT
    with pytest.raises(ValueError, match="timeout_s"):
        TimeoutCriterion(-1.0)


def test_lights_cycle_with_opposite_approaches_together() -> None:
    lanes = get_town("square").lanes
    lights = TrafficLights(lanes)
    lights.reset(np.random.default_rng(0))
    centre = [a.light for a in lanes.approaches if a.node == 8]  # node "o": the crossing
    assert len(centre) == 4
    seen = set()
    for t in np.arange(0.0, 80.0, 0.5):
        codes = lights.update(float(t))[centre]
        greens = [i for i, c in zip(centre, codes, strict=True) if c == GREEN]
        if greens:
            yaws = [lanes.approaches[i].yaw for i in greens]
            assert len(greens) == 2 and abs(math.cos(yaws[0] - yaws[1]) + 1) < 1e-6
        seen |= set(codes.tolist())
        assert np.sum(codes != RED) <= 2
    assert seen == {0, 1, 2}
    other = TrafficLights(lanes)
    other.reset(np.random.default_rng(1))
    assert not np.array_equal(other.update(5.0), lights.update(5.0)) or not np.array_equal(other.offset, lights.offset)


def _drive(w: EmbeddedWorld, control: Control, steps: int) -> list[Event]:
    events: list[Event] = []
    for _ in range(steps):
        events += w.step(control).events
    return events


def test_world_reports_lane_invasion_collision_and_red_light() -> None:
    w = EmbeddedWorld()
    # south spoke of the square, heading north, steering left into the opposite lane then off the road
    w.reset(Scenario(town="square", start=Pose(1.75, -50.0, math.pi / 2), goal=Pose(1.75, -20.0, math.pi / 2),
                     camera=False), seed=0)
    w.ego.speed = 5.0
    ev = _drive(w, Control(steer=-0.15, throttle=0.2), 40)
    details = [e.detail for e in ev if e.kind is EventKind.LANE_INVASION]
    assert details[:2] == ["opposite_lane", "off_road"]
    # run a red light: force the route's first light red and drive over its stop line
    w.reset(Scenario(town="square", start=Pose(1.75, -40.0, math.pi / 2), goal=Pose(1.75, 30.0, math.pi / 2),
                     camera=False), seed=0)
    light = w.route.lights[0][1]
    w.lights.offset[:] = 0.0
    w.lights.start[:] = 60.0  # every approach's slot starts late in its cycle: red until then
    w.ego.speed = 8.0
    ev = _drive(w, Control(throttle=0.5), 40)
    kinds = [(e.kind, e.other_id) for e in ev]
    assert (EventKind.RED_LIGHT, light) in kinds and (EventKind.LIGHT_PASSED, light) in kinds


def test_world_collides_with_buildings() -> None:
    town = get_town("square")
    b = town.geometry.buildings[0]
    w = EmbeddedWorld()
    w.reset(Scenario(town="square", camera=False), seed=0)
    w.ego.x, w.ego.y, w.ego.yaw = b.x - 10.0 * math.cos(b.yaw), b.y - 10.0 * math.sin(b.yaw), b.yaw
    w.ego.speed = 6.0
    ev = [e for e in _drive(w, Control(throttle=0.3), 30) if e.kind is EventKind.COLLISION]
    assert ev and ev[0].other_type == "static" and ev[0].other_id is None
