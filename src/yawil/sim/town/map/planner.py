"""Route planning on the lane graph, with road options as CARLA's global/local planner give them.

A route is the shortest lane sequence between two snapped poses, sampled every metre. Options: LANEFOLLOW on
road lanes and corner curves; LEFT/RIGHT/STRAIGHT on junction connectors and on the last `PRE_JUNCTION`
metres before them (where CARLA's local planner already announces the manoeuvre).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from yawil.sim.town.map.lanes import LaneGraph
from yawil.sim.types import Pose, RoadOption, Route

PRE_JUNCTION = 5.0  # metres before a junction connector that already carry its option
WAYPOINT_STEP = 1.0
GOAL_REACH = 5.0  # m past the goal a car's front bumper may reach when it stops there: a light within it counts


@dataclass(frozen=True)
class PlannedRoute:
    """A Route plus what the backend needs internally: the lane and arc length of each waypoint."""

    route: Route
    lanes: np.ndarray  # (N,) lane id per waypoint
    s: np.ndarray  # (N,) arc length on that lane
    lane_sequence: tuple[int, ...]


def _graph(lanes: LaneGraph):  # type: ignore[no-untyped-def]
    g = getattr(lanes, "_nx", None)
    if g is None:
        import networkx as nx

        g = nx.DiGraph()
        g.add_nodes_from(range(len(lanes.lanes)))
        for ln in lanes.lanes:
            for nxt in ln.successors:
                g.add_edge(ln.id, nxt, weight=ln.length)
        lanes._nx = g  # type: ignore[attr-defined]
    return g


def plan_route(lanes: LaneGraph, start: Pose, goal: Pose) -> PlannedRoute:
    """Shortest route from start to goal, each snapped to the nearest lane of matching direction."""
    import networkx as nx

    ls, ss, _ = lanes.snap(start.x, start.y, start.yaw)
    lg, sg, _ = lanes.snap(goal.x, goal.y, goal.yaw)
    if ls == lg and sg >= ss:
        seq = [ls]
    else:
        g = _graph(lanes)
        try:
            _, path = nx.multi_source_dijkstra(g, set(lanes.lanes[ls].successors), target=lg, weight="weight")
        except (nx.NetworkXNoPath, ValueError):
            raise ValueError(
                f"goal {goal} is unreachable from start {start} on town {lanes.layout.name!r}"
            ) from None
        seq = [ls, *path]
    return sample_route(lanes, seq, ss, sg)


def stations(total: float) -> np.ndarray:
    """Arc lengths of a route's waypoints: every WAYPOINT_STEP metres, plus the end, so the goal is a waypoint."""
    d = np.arange(0.0, total, WAYPOINT_STEP)
    return np.append(d, total) if total - d[-1] > 1e-6 else d


def sample_route(lanes: LaneGraph, seq: list[int], s_start: float, s_goal: float) -> PlannedRoute:
    """Dense waypoints along a lane sequence from s_start on the first lane to s_goal on the last."""
    lo = np.array([s_start] + [0.0] * (len(seq) - 1))
    hi = np.array([lanes.length[i] for i in seq])
    hi[-1] = s_goal
    seg_len = np.maximum(hi - lo, 0.0)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = float(cum[-1])
    if total < 1.0:
        raise ValueError(f"route is only {total:.2f} m long; start and goal must be at least 1 m apart along the lanes")
    d = stations(total)
    seg = np.clip(np.searchsorted(cum, d, side="right") - 1, 0, len(seq) - 1)
    lane_ids = np.array(seq)[seg]
    s_local = lo[seg] + (d - cum[seg])
    xy = np.empty((len(d), 2))
    yaw = np.empty(len(d))
    options = np.empty(len(d), dtype=np.int8)
    for k in np.unique(seg):
        m = seg == k
        lane = lanes.lanes[seq[k]]
        xy[m], yaw[m] = lane.evaluate(s_local[m])
        options[m] = int(lane.option)
    for k, lid in enumerate(seq):
        opt = lanes.lanes[lid].option
        if opt is RoadOption.LANEFOLLOW:
            continue
        before = (d >= cum[k] - PRE_JUNCTION) & (d < cum[k]) & (options == int(RoadOption.LANEFOLLOW))
        options[before] = int(opt)
    lights: list[tuple[int, int]] = []
    for k, lid in enumerate(seq):
        light = int(lanes.light_of_lane[lid])
        if light < 0:
            continue
        stop_s = lanes.approaches[light].stop_s
        if stop_s < lo[k] or (k == len(seq) - 1 and stop_s > hi[k] + GOAL_REACH):
            continue  # behind the start, or beyond the reach of a car stopping at the goal
        dist = cum[k] + stop_s - lo[k]
        lights.append((int(min(np.searchsorted(d, dist), len(d) - 1)), light))
    route = Route(xy=xy, options=options, lane_yaw=yaw, lights=tuple(lights))
    return PlannedRoute(route, lane_ids, s_local, tuple(seq))


def _between(lanes: LaneGraph) -> np.ndarray:
    """D[a, b]: metres from the end of lane a to the start of lane b by the shortest lane sequence."""
    d = getattr(lanes, "_between", None)
    if d is None:
        import networkx as nx

        sp = nx.floyd_warshall_numpy(_graph(lanes), nodelist=range(len(lanes.lanes)), weight="weight")
        d = np.full_like(sp, np.inf)
        for a, ln in enumerate(lanes.lanes):
            d[a] = np.min(sp[ln.successors], axis=0)
        lanes._between = d  # type: ignore[attr-defined]
    return d


def random_route(lanes: LaneGraph, rng: np.random.Generator, min_length: float = 0.0, max_tries: int = 5000,
                 start: Pose | None = None, goal: Pose | None = None) -> PlannedRoute:
    """A route between random road-lane points (or the given start/goal), redrawn until min_length long."""
    import networkx as nx

    between = _between(lanes)
    fixed_start = lanes.snap(start.x, start.y, start.yaw)[:2] if start is not None else None
    fixed_goal = lanes.snap(goal.x, goal.y, goal.yaw)[:2] if goal is not None else None
    n = lanes.n_road_lanes
    longest = float(np.max(lanes.length[:n, None] + between[:n, :n] + lanes.length[None, :n]))
    if longest < min_length:
        raise ValueError(f"no route of at least {min_length:.0f} m exists on town {lanes.layout.name!r} "
                         f"(longest about {longest:.0f} m)")
    for _ in range(max_tries):
        ls, lg = (int(v) for v in rng.integers(0, n, size=2))
        ss = float(rng.uniform(0.1, 0.6) * lanes.length[ls])
        sg = float(rng.uniform(0.4, 0.9) * lanes.length[lg])
        if fixed_start is not None:
            ls, ss = fixed_start
        if fixed_goal is not None:
            lg, sg = fixed_goal
        direct = ls == lg and sg > ss + 1.0
        length = sg - ss if direct else lanes.length[ls] - ss + between[ls, lg] + sg
        if not np.isfinite(length) or length < min_length:
            continue
        if direct:
            seq = [ls]
        else:
            _, path = nx.multi_source_dijkstra(_graph(lanes), set(lanes.lanes[ls].successors), target=lg, weight="weight")
            seq = [ls, *path]
        return sample_route(lanes, seq, ss, sg)
    raise ValueError(
        f"no route of at least {min_length:.0f} m found on town {lanes.layout.name!r} in {max_tries} draws "
        f"(from the given start/goal, if any)"
    )


def route_endpoints(planned: PlannedRoute) -> tuple[Pose, Pose]:
    """Start and goal poses of a planned route (what a route file stores)."""
    r = planned.route
    return (Pose(float(r.xy[0, 0]), float(r.xy[0, 1]), float(r.lane_yaw[0])),
            Pose(float(r.xy[-1, 0]), float(r.xy[-1, 1]), float(r.lane_yaw[-1])))


@dataclass(frozen=True)
class TurnTask:
    """One turning manoeuvre of a town (the square scene's 32 tasks)."""

    name: str
    kind: str  # "corner" | "tjunction" | "crossing"
    option: RoadOption  # LANEFOLLOW for corners, LEFT/RIGHT at junctions
    direction: str  # "left" | "right"
    start: Pose
    goal: Pose


def turn_tasks(lanes: LaneGraph, lead_in: float = 25.0, lead_out: float = 25.0) -> list[TurnTask]:
    """Every turning connector (corners both ways, junction left/right turns) as a start/goal task."""
    tasks: list[TurnTask] = []
    kinds = {2: "corner", 3: "tjunction", 4: "crossing"}
    for ln in lanes.lanes[lanes.n_road_lanes :]:
        entry, exit_ = lanes.lanes[ln.entry], lanes.lanes[ln.exit]
        h0 = float(entry.evaluate(np.array([entry.length]))[1][0])
        h1 = float(exit_.evaluate(np.array([0.0]))[1][0])
        turn = math.remainder(h1 - h0, 2 * math.pi)
        if ln.option is RoadOption.STRAIGHT or abs(turn) < math.radians(30):
            continue
        s0 = max(0.0, entry.length - lead_in)
        s1 = min(exit_.length, lead_out)
        (p0,), (y0,) = entry.evaluate(np.array([s0]))
        (p1,), (y1,) = exit_.evaluate(np.array([s1]))
        direction = "left" if turn > 0 else "right"
        key = lanes.layout.nodes[ln.node][0]
        kind = kinds[int(lanes.degree[ln.node])]
        tasks.append(TurnTask(f"{kind}-{key}-{direction}-from-{lanes.layout.nodes[entry.start_node][0]}", kind,
                              ln.option, direction, Pose(float(p0[0]), float(p0[1]), float(y0)),
                              Pose(float(p1[0]), float(p1[1]), float(y1))))
    return tasks


def square_tasks() -> list[TurnTask]:
    """The square scene's 32 turning tasks: 8 corner, 16 T-junction and 8 crossing turns."""
    from yawil.sim.town.map.town import get_town

    tasks = turn_tasks(get_town("square").lanes)
    if len(tasks) != 32:  # pragma: no cover - guards edits of square.json
        raise ValueError(f"square.json yields {len(tasks)} turning tasks, expected 32")
    return tasks
