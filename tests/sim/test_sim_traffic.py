"""Vehicles and pedestrians: no overlaps, lights obeyed, junctions yielded, the ego respected, walkways kept."""

from __future__ import annotations

import math

import numpy as np
import pytest

from yawil.sim import Control, EventKind, Pose, RoadOption, Scenario
from yawil.sim.criteria import boxes_overlap
from yawil.sim.town.map.lanes import LaneGraph
from yawil.sim.town.map.regions import GROUND
from yawil.sim.town.map.town import get_town
from yawil.sim.town.traffic.lights import GREEN, LINKED_GREEN, RED, TrafficLights
from yawil.sim.town.traffic.pedestrians import SIZE, Pedestrians
from yawil.sim.town.traffic.vehicles import Vehicles
from yawil.sim.town.world import EmbeddedWorld


def test_dense_traffic_keeps_the_rules() -> None:
    w = EmbeddedWorld()
    w.reset(Scenario(town="town02", vehicles=50, pedestrians=30, camera=False), seed=4)
    veh, ped, lanes = w.vehicles, w.pedestrians, w.town.lanes  # type: ignore[union-attr]
    assert veh.n == 50 and ped.n == 30
    ego = w.ego_box()
    boxes = np.stack([veh.x, veh.y, veh.yaw, veh.length, veh.width], 1)
    assert not boxes_overlap(ego, boxes).any()  # never spawned on the ego
    start = veh.x.copy(), veh.y.copy()
    regions = w.town.regions  # type: ignore[union-attr]
    exit_lanes = np.array([ln.id for ln in lanes.lanes[: lanes.n_road_lanes] if lanes.degree[ln.start_node] >= 3])
    for _ in range(400):
        lane_before, front_before = veh.lane.copy(), veh.s + veh.length / 2
        w.step(Control(brake=1.0))
        boxes = np.stack([veh.x, veh.y, veh.yaw, veh.length - 0.2, veh.width - 0.2], 1)
        for i in range(veh.n):  # no two vehicles overlap
            assert not boxes_overlap(boxes[i], np.delete(boxes, i, axis=0)).any()
        # nobody crosses a stop line on red
        light = lanes.light_of_lane[lane_before]
        same = veh.lane == lane_before
        stop = veh.stop_s[lane_before]
        crossed = same & (light >= 0) & (front_before < stop - 0.5) & (veh.s + veh.length / 2 > stop + 0.5)
        assert not np.any(crossed & (w.lights.codes[np.maximum(light, 0)] == RED))
        # at most one of any conflicting pair of junction connectors is in use
        on = np.unique(veh.lane[veh.lane >= lanes.n_road_lanes])
        assert not lanes.conflict[np.ix_(on, on)].any()
        # don't block the box: what is on a junction's exit lane or queued towards it fits on that lane
        conn = veh.lane >= lanes.n_road_lanes
        load = np.bincount(np.where(conn, veh.exit_of[veh.lane], veh.lane), weights=veh.length + veh.S0,
                           minlength=len(lanes.lanes))
        assert np.all(load[exit_lanes] <= lanes.length[exit_lanes] + 1e-6)
        # pedestrians stay on walkways (sidewalks, crosswalks, or the road while jaywalking)
        assert not np.any(regions.query(ped.xy[:, 0], ped.xy[:, 1]) == GROUND)
    moved = np.hypot(veh.x - start[0], veh.y - start[1])
    assert np.median(moved) > 40.0  # traffic flows (400 steps = 40 s)
    assert np.hypot(*(ped.xy - ped.target).T).max() < 200


def test_vehicle_stops_behind_the_ego_and_for_pedestrians() -> None:
    lanes = get_town("square").lanes
    lane = lanes.road_lanes[0][0]  # sw -> s, along the bottom, heading east
    for obstacle in ("ego", "pedestrian"):
        v = Vehicles(lanes)
        v._alloc(1)
        v.lane[:] = lane
        v.s[:] = 2.0
        v.v[:] = 8.0
        v.v0[:] = 8.0
        v.nxt1[:] = lanes.lanes[lane].successors[0]
        v.nxt2[:] = lanes.lanes[int(v.nxt1[0])].successors[0]
        v.length[:], v.width[:] = 4.5, 1.8
        v._update_pose()
        (ox,), (oy,), (oyaw,) = lanes.lookup(np.array([lane]), np.array([30.0]))
        far = (1e4, 1e4, 0.0, 0.0)
        for _ in range(150):
            if obstacle == "ego":
                v.step(0.1, np.random.default_rng(0), np.zeros(len(lanes.approaches), dtype=np.int64),
                       (ox, oy, oyaw, 0.0), (4.6, 1.9), np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
            else:
                v.step(0.1, np.random.default_rng(0), np.zeros(len(lanes.approaches), dtype=np.int64), far,
                       (4.6, 1.9), np.zeros(0, dtype=np.int64), np.array([[ox, oy]]))
        assert v.v[0] < 0.05
        gap = 30.0 - v.s[0] - 4.5 / 2 - (4.6 / 2 if obstacle == "ego" else 0.3)
        assert 0.5 < gap < 6.0, (obstacle, gap)


def test_traffic_yields_to_the_ego_in_a_junction() -> None:
    """With the ego parked inside the central crossing, no vehicle enters a connector crossing its spot."""
    w = EmbeddedWorld()
    w.reset(Scenario(town="square", vehicles=30, camera=False), seed=2)
    w.ego.x, w.ego.y, w.ego.yaw, w.ego.speed = 0.0, 0.0, math.pi / 2, 0.0
    lanes = w.town.lanes  # type: ignore[union-attr]
    taken = w._ego_connectors()
    assert len(taken) >= 4
    blocked = lanes.conflict[taken].any(axis=0) | np.isin(np.arange(len(lanes.lanes)), taken)
    inside_before = set(np.flatnonzero(blocked[w.vehicles.lane]).tolist())
    for _ in range(300):
        w.step(Control(brake=1.0))
        now = set(np.flatnonzero(blocked[w.vehicles.lane]).tolist())
        assert now <= inside_before  # only those already inside may still be there
        inside_before &= now


def test_pedestrians_cross_roads_and_sometimes_jaywalk() -> None:
    w = EmbeddedWorld()
    w.reset(Scenario(town="square", pedestrians=40, camera=False), seed=9)
    ped = w.pedestrians
    ped.jaywalk_per_s = 0.05
    crossing, jay = 0, 0
    for _ in range(600):
        w.step(Control(brake=1.0))
        crossing += int(np.sum(ped.on_road & (ped.dest >= 0)))
        jay += int(np.sum(ped.dest < 0))
    assert crossing > 0 and jay > 0


def test_ego_can_hit_a_vehicle() -> None:
    w = EmbeddedWorld()
    w.reset(Scenario(town="square", start=Pose(1.75, -50.0, math.pi / 2), goal=Pose(1.75, -20.0, math.pi / 2),
                     vehicles=0, camera=False), seed=0)
    v = w.vehicles
    v._alloc(1)
    lane, s, _ = w.town.lanes.snap(1.75, -40.0, math.pi / 2)  # type: ignore[union-attr]
    v.lane[:], v.s[:] = lane, s
    v.nxt1[:] = w.town.lanes.lanes[lane].successors[0]  # type: ignore[union-attr]
    v.nxt2[:] = w.town.lanes.lanes[int(v.nxt1[0])].successors[0]  # type: ignore[union-attr]
    v.length[:], v.width[:], v.v0[:] = 4.5, 1.8, 0.01
    v._update_pose()
    w.ego.speed = 8.0
    hits = [e for _ in range(30) for e in w.step(Control(throttle=0.5)).events if e.kind is EventKind.COLLISION]
    assert hits and hits[0].other_type == "vehicle" and hits[0].other_id == int(v.ids[0])


# ---------------------------------------------------------------- regressions of the expert's findings
def _one_vehicle(lanes: LaneGraph, lane: int, s: float, v: float, nxt1: int) -> Vehicles:
    veh = Vehicles(lanes)
    veh._alloc(1)
    veh.lane[:], veh.s[:], veh.v[:], veh.v0[:] = lane, s, v, 8.0
    veh.nxt1[:] = nxt1
    veh.nxt2[:] = lanes.lanes[nxt1].successors[0]
    veh.length[:], veh.width[:] = 4.5, 1.8
    veh._update_pose()
    return veh


def test_jaywalker_does_not_step_in_front_of_or_into_a_standing_ego() -> None:
    """Finding 1 (town02 seeds 8, 20, 39, 40): a jaywalker crossed straight through the standing ego."""
    town = get_town("square")
    walk = town.walkways
    ped = Pedestrians(walk, jaywalk_per_s=1e4)  # jaywalks at the first chance
    ped.spawn(1, np.random.default_rng(0), keep_out=[])
    e = next(k for k in range(len(walk.edges)) if walk.edge_twin[k] >= 0)
    a, b = walk.edges[e]
    ped.xy[0] = (walk.xy[a] + walk.xy[b]) / 2
    ped.target[0], ped.dest[0], ped.prev[0], ped.edge[0] = walk.xy[b], b, a, e
    ped.speed[0] = 0.0  # stands on its sidewalk until it crosses
    twin = walk.edges[walk.edge_twin[e]]
    far_side = (walk.xy[twin[0]] + walk.xy[twin[1]]) / 2
    mid = (ped.xy[0] + far_side) / 2  # the road's centre line, where it would cross
    u = walk.xy[b] - walk.xy[a]
    ego = np.array([[mid[0], mid[1], math.atan2(u[1], u[0]), 4.6, 1.9, 0.0]])
    rng = np.random.default_rng(1)
    for _ in range(50):  # the ego stands on the crossing: it waits on the sidewalk
        ped.step(0.1, rng, ego)
        assert not ped.on_road[0]
    ped.speed[0] = 1.3
    for _ in range(5):  # the road is clear: it goes
        ped.step(0.1, rng, np.zeros((0, 6)))
    assert ped.on_road[0] and ped.dest[0] == -1
    start = ped.xy[0].copy()
    ped.jaywalk_per_s = 0.0  # once back, it would try again further along
    closest, waited = math.inf, 0
    for _ in range(120):  # a car pulls up across its way: it stops short, then turns back
        ped.step(0.1, rng, ego)
        closest = min(closest, float(Pedestrians._box_distance(ped.xy[:1], ego[:, :5])[0, 0]))
        waited += int(ped.on_road[0] and ped.v[0] == 0.0)  # observers see it standing, not walking
    assert closest > SIZE / 2 and waited >= 30
    assert not ped.on_road[0] and ped.edge[0] == e and ped.dest[0] >= 0  # back on its own sidewalk
    # a vehicle coming at 8 m/s from 20 m away is too close to cross in front of; one 80 m away is not
    heading = math.atan2(u[1], u[0])
    for dist, clear in ((20.0, False), (80.0, True)):
        x, y = mid - dist * u / np.hypot(*u)
        car = np.array([[x, y, heading, 4.5, 1.8, 8.0]])
        assert Pedestrians._crossing_clear(start, far_side, np.array([1.3]), car)[0] == clear
    # a car standing with its bumper 0.8 m short of the crossing (stopped a little over its stop line) does
    # not keep pedestrians at the kerb: they pass in front of it (else it and they wait for each other)
    x, y = mid - (2.3 + 0.8) * u / np.hypot(*u)
    assert Pedestrians._crossing_clear(start, far_side, np.array([1.3]), np.array([[x, y, heading, 4.6, 1.9, 0.0]]))[0]


def test_no_vehicle_enters_a_junction_without_room_after_it() -> None:
    """Finding 2 (town02 seed 0): vehicles entered connectors onto the full 20 m block between x = 90 and 110 m."""
    lanes = get_town("town02").lanes
    exit_lane = 10  # 20 m, from the junction at x = 90 to the one at x = 110
    conn = next(c for c in lanes.node_connectors[lanes.lanes[exit_lane].start_node] if lanes.lanes[c].exit == exit_lane)
    entry = lanes.lanes[conn].entry
    veh = Vehicles(lanes)
    veh._alloc(3)
    # two cars on the block, not yet at its end, and one arriving
    veh.lane[:] = (exit_lane, exit_lane, entry)
    veh.s[:] = (17.5, 11.0, lanes.length[entry] - 12.0)
    veh.v[:] = (1.0, 1.0, 6.0)
    veh.v0[:] = (0.01, 0.01, 8.0)  # the two come to a halt there (as behind a queue at the next junction)
    veh.nxt1[:] = [lanes.lanes[exit_lane].successors[0]] * 2 + [conn]
    veh.nxt2[:] = [lanes.lanes[int(n)].successors[0] for n in veh.nxt1]
    veh.length[:], veh.width[:] = 4.5, 1.8
    veh._update_pose()
    assert veh._exit_room((-1, 0.0), 4.6)[exit_lane] < 4.5 + veh.S0 + 1.0  # two cars' queue leaves no room
    codes = np.full(len(lanes.approaches), RED, dtype=np.int64)
    codes[lanes.light_of_lane[entry]] = 0  # green for the arriving car, red ahead of the two on the block
    far = (1e4, 1e4, 0.0, 0.0)
    for _ in range(200):
        veh.step(0.1, np.random.default_rng(0), codes, far, (4.6, 1.9), np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
        assert veh.lane[2] == entry  # it waits before the box, although the block's start looked free
    assert veh.v[2] < 0.05


def test_turning_vehicle_looks_along_its_own_path_for_the_ego() -> None:
    """Finding 3 (town01 seed 20): a left-turning car stopped for the ego straight ahead of its bonnet."""
    lanes = get_town("square").lanes
    left = 58  # centre junction: from the south (lane 16, heading north) left to the west (lane 23)
    entry = lanes.lanes[left].entry
    green = np.zeros(len(lanes.approaches), dtype=np.int64)
    none = np.zeros(0, dtype=np.int64)
    # the ego stands 20 m straight ahead (on the crossing's straight connector), 1.5 m clear of the turn
    veh = _one_vehicle(lanes, entry, lanes.length[entry] - 8.0, 5.0, left)
    ego = (float(veh.x[0]), float(veh.y[0]) + 20.0, math.pi / 2, 0.0)
    slowest = math.inf
    for _ in range(60):
        veh.step(0.1, np.random.default_rng(0), green, ego, (4.6, 1.9), none, np.zeros((0, 2)))
        slowest = min(slowest, float(veh.v[0]))
    assert veh.lane[0] == lanes.lanes[left].exit and slowest > 4.5  # turned at its turning speed
    # the ego stands on the turn itself: the car stops short of it
    (mx,), (my,), (myaw,) = lanes.lookup(np.array([left]), np.array([lanes.length[left] / 2]))
    veh = _one_vehicle(lanes, entry, lanes.length[entry] - 8.0, 5.0, left)
    for _ in range(100):
        veh.step(0.1, np.random.default_rng(0), green, (mx, my, myaw, 0.0), (4.6, 1.9), none, np.zeros((0, 2)))
    boxes = np.array([[veh.x[0], veh.y[0], veh.yaw[0], 4.5, 1.8]])
    assert veh.v[0] < 0.05 and not boxes_overlap((mx, my, myaw, 4.6, 1.9), boxes).any()


def test_a_queue_head_starved_of_exit_room_reserves_it() -> None:
    """A head waiting 10 s for room on a 20 m block keeps it from the other approach (town02 seed 30 starved)."""
    lanes = get_town("town02").lanes
    exit_lane = 11  # 20 m
    conns = [c for c in lanes.node_connectors[lanes.lanes[exit_lane].start_node] if lanes.lanes[c].exit == exit_lane]
    (ca, cb) = conns[:2]
    ea, eb = lanes.lanes[ca].entry, lanes.lanes[cb].entry
    for waited, other_enters in ((0.0, True), (11.0, False)):
        veh = Vehicles(lanes)
        veh._alloc(3)
        veh.lane[:] = (exit_lane, ea, eb)
        veh.s[:] = (12.0, veh.stop_s[ea] - 2.25 - 2.6, lanes.length[eb] - 15.0)
        veh.v[:] = (0.0, 0.0, 6.0)
        veh.v0[:] = (0.01, 8.0, 8.0)  # one car stands on the block: room for exactly one more
        veh.nxt1[:] = (lanes.lanes[exit_lane].successors[0], ca, cb)
        veh.nxt2[:] = [lanes.lanes[int(n)].successors[0] for n in veh.nxt1]
        veh.length[:], veh.width[:] = 4.5, 1.8
        veh.wait[1] = waited
        veh._update_pose()
        codes = np.full(len(lanes.approaches), RED, dtype=np.int64)
        codes[lanes.light_of_lane[eb]] = 0  # green for the other approach, red for the waiting head
        far, none, no_ped = (1e4, 1e4, 0.0, 0.0), np.zeros(0, dtype=np.int64), np.zeros((0, 2))
        entered = False
        for _ in range(100):
            veh.step(0.1, np.random.default_rng(0), codes, far, (4.6, 1.9), none, no_ped)
            entered |= bool(veh.lane[2] == cb)
        assert entered is other_enters
        if not other_enters:  # the head's green comes: the room it kept is its own
            codes[lanes.light_of_lane[ea]] = 0
            codes[lanes.light_of_lane[eb]] = RED
            for _ in range(100):
                veh.step(0.1, np.random.default_rng(0), codes, far, (4.6, 1.9), none, no_ped)
            assert veh.lane[1] in (ca, exit_lane)


def test_pedestrian_at_a_blocked_crosswalk_walks_elsewhere() -> None:
    """A car standing on the crosswalk: the pedestrian waits at the kerb, then (15 s) goes another way."""
    walk = get_town("square").walkways
    e = walk.edge_kind.index("crosswalk")
    a, b = (int(k) for k in walk.edges[e])
    ped = Pedestrians(walk, jaywalk_per_s=0.0)
    ped.spawn(1, np.random.default_rng(0), keep_out=[])
    ped.xy[0], ped.target[0], ped.prev[0], ped.dest[0], ped.edge[0] = walk.xy[a], walk.xy[b], a, b, e
    ped.kerb[0], ped.on_road[0], ped.speed[0] = True, False, 1.3
    u = walk.xy[b] - walk.xy[a]
    mid = (walk.xy[a] + walk.xy[b]) / 2
    car = np.array([[mid[0], mid[1], math.atan2(u[0], -u[1]), 4.5, 1.8, 0.0]])  # across the crosswalk
    rng = np.random.default_rng(3)
    for _ in range(140):
        ped.step(0.1, rng, car)
        assert not ped.on_road[0] and np.array_equal(ped.xy[0], walk.xy[a])  # waits at its kerb
    for _ in range(40):
        ped.step(0.1, rng, car)
    assert ped.dest[0] != b and np.hypot(*(ped.xy[0] - walk.xy[a])) > 1.0


def test_no_vehicle_pulls_out_across_an_ego_committed_to_a_junction() -> None:
    """Town02 regular route 8 seed 1: the ego's nose was in the box at 5 m/s when a car waiting at the opposite
    entry turned left across it; each then stood in the other's path until the timeout (route 10 seed 2: the
    same with the ego 2 m before the box at 3.3 m/s)."""
    w = EmbeddedWorld()
    w.reset(Scenario(town="town02", vehicles=0, pedestrians=0, camera=False), seed=0)
    lanes, lights = w.town.lanes, w.lights  # type: ignore[union-attr]
    west, east = 13, 10  # into the junction at x = 120 m: from the east (y = 101.75), from the 20 m block
    node = lanes.lanes[west].end_node
    left = next(c for c in lanes.node_connectors[node]
                if lanes.lanes[c].entry == east and lanes.lanes[c].option is RoadOption.LEFT)
    veh = _one_vehicle(lanes, east, float(lanes.length[east]), 0.0, left)  # waiting at its junction entry
    w.vehicles = veh
    group = lights.group[lanes.light_of_lane[east]]
    assert lights.group[lanes.light_of_lane[west]] == group  # opposite approaches: both green
    lights.offset[lights.node == node] = lights.start[lanes.light_of_lane[east]] + 1.0
    box = float(lanes.lanes[west].ctrl[3, 0])  # x where the ego's lane meets the junction
    # (front bumper to the box, speed): in it within 2 s or unable to stop comfortably short of it
    for gap, speed, committed in ((2.1, 3.3, True), (8.0, 3.3, False), (1.0, 0.0, False), (1.0, 5.0, True)):
        w.ego.x, w.ego.y, w.ego.yaw, w.ego.speed = box + 2.3 + gap, 101.75, math.pi, speed
        assert (len(w._ego_connectors()) > 0) is committed

    while w.ego.x > box - 20.0:  # the ego drives straight through
        w.step(Control(throttle=0.3))
        if w.ego.x > lanes.node_xy[node][0] - 3.0:  # still before or on the left turn's path
            assert veh.lane[0] == east
    for _ in range(30):
        w.step(Control(brake=1.0))
    assert veh.lane[0] != east  # then it turns


def test_lights_at_both_ends_of_a_short_block_turn_green_together() -> None:
    """Town02's 20 m block held two cars a cycle while its two junctions' phases ran at random offsets, and the
    queues behind it spilled over the town (dense traffic, seed 31 timed out in them)."""
    lanes = get_town("town02").lanes
    lights = TrafficLights(lanes)
    into_n4, block_e, into_n5, block_w = (int(lanes.light_of_lane[i]) for i in (8, 10, 13, 11))
    for seed in range(5):
        lights.reset(np.random.default_rng(seed))
        for t in np.arange(0.0, 40.0, 0.5):
            codes = lights.update(float(t))
            assert codes[into_n4] == codes[block_e] == codes[into_n5] == codes[block_w]
    assert len(lights.links) == 1  # only the 20 m block between x = 90 and 110 m
    # the phase along the block gets the longer green; the stems keep the usual one
    stem = next(i for i in range(len(lights.node)) if lights.node[i] == lights.node[into_n4]
                and lights.group[i] != lights.group[into_n4])
    times = np.arange(0.0, lights.cycle[into_n4], 0.1)
    green = {i: sum(lights.update(float(t))[i] == GREEN for t in times) * 0.1 for i in (into_n4, block_w, stem)}
    assert green[into_n4] == pytest.approx(LINKED_GREEN, abs=0.11) and green[block_w] == pytest.approx(LINKED_GREEN, abs=0.11)
    assert green[stem] == pytest.approx(lights.green, abs=0.11) and lights.green < LINKED_GREEN
    for town in ("town01", "square"):  # no short block: every junction keeps its own random offset
        assert TrafficLights(get_town(town).lanes).links == []


def test_the_ego_waiting_for_exit_room_reserves_it_like_a_vehicle() -> None:
    """Town02 seed 26: the ego waited at the north approach to turn onto the 20 m block, which the straight
    traffic sharing the block's green refilled every cycle; vehicles reserved room, the ego could not."""
    lanes = get_town("town02").lanes
    exit_lane = 11
    cb = [c for c in lanes.node_connectors[lanes.lanes[exit_lane].start_node] if lanes.lanes[c].exit == exit_lane][1]
    eb = lanes.lanes[cb].entry
    far, none, no_ped = (1e4, 1e4, 0.0, 0.0), np.zeros(0, dtype=np.int64), np.zeros((0, 2))
    for ego_waited, other_enters in ((0.0, True), (11.0, False)):
        veh = Vehicles(lanes)
        veh._alloc(2)
        veh.lane[:] = (exit_lane, eb)
        veh.s[:] = (12.0, lanes.length[eb] - 15.0)
        veh.v[:] = (0.0, 6.0)
        veh.v0[:] = (0.01, 8.0)  # one car stands on the block: room for exactly one more
        veh.nxt1[:] = (lanes.lanes[exit_lane].successors[0], cb)
        veh.nxt2[:] = [lanes.lanes[int(n)].successors[0] for n in veh.nxt1]
        veh.length[:], veh.width[:] = 4.5, 1.8
        veh.ego_wait = ego_waited
        veh._update_pose()
        codes = np.zeros(len(lanes.approaches), dtype=np.int64)  # green for the other car
        entered = False
        for _ in range(100):
            veh.step(0.1, np.random.default_rng(0), codes, far, (4.6, 1.9), none, no_ped, ego_gate=(exit_lane, True))
            entered |= bool(veh.lane[1] == cb)
        assert entered is other_enters
        assert veh.ego_wait > ego_waited + 5.0  # counted while the room lacked
