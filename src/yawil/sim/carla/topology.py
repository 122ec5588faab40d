"""Route planning on a CARLA map's topology with networkx, as CARLA's GlobalRoutePlanner does it.

The `agents` package is not in the client wheel, so its planner is re-done here on PLAIN data: a map is a
list of segments (what `carla.Map.get_topology()` pairs become once each is sampled every metre with
`waypoint.next(1.0)`), each a list of waypoint tuples `(x, y, z, yaw_deg, road_id, lane_id, is_junction)` in
CARLA's left-handed frame. `from_carla_map` is the thin adapter from a live (or OpenDRIVE-built) carla.Map;
`from_json` reads a recorded description. Everything else runs without the `carla` package.

As GlobalRoutePlanner: graph nodes are segment end points rounded to the metre; an edge is a segment,
weighted by its length; its `intersection` flag is its entry waypoint's `is_junction`. The road option of a
junction segment comes from `_turn_decision`: STRAIGHT when the heading changes by less than 35 deg between
the exit of the approach and the exit of the junction, else LEFT/RIGHT from the sign of the cross product
compared with the other branches (signs flipped, since we compute in yawil's right-handed frame). Lane
changes are not planned (Town01 and Town02 have one lane per direction). As yawil's embedded planner, the
route is then resampled every metre and the last 5 m before a junction carry its option already.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np

from yawil.fileio import write_atomic
from yawil.sim.carla.convert import xy_from_carla, yaw_from_carla
from yawil.sim.town.map.planner import GOAL_REACH, PRE_JUNCTION, WAYPOINT_STEP, stations
from yawil.sim.types import Pose, RoadOption, Route, wrap_angle

MAP_FORMAT = "yawil-carla-map/1"
TURN_THRESHOLD = math.radians(35.0)  # GlobalRoutePlanner's straight/turn threshold
SAMPLING = 1.0  # metres between the waypoints of a segment (waypoint.next(1.0))
STOP_MATCH_M = 2.0  # a stop line belongs to a route waypoint within this distance...
STOP_MATCH_COS = math.cos(math.radians(45.0))  # ...whose heading is within 45 deg of the light's

WaypointTuple = tuple[float, float, float, float, int, int, bool]
Node = tuple[float, float, float]


@dataclass(frozen=True)
class Segment:
    """One topology edge in yawil's frame, sampled at most SAMPLING metres apart."""

    xy: np.ndarray  # (n, 2)
    z: np.ndarray  # (n,)
    yaw: np.ndarray  # (n,) lane heading, radians (the "simulator yaw")
    road: np.ndarray  # (n,) int road_id
    lane: np.ndarray  # (n,) int lane_id
    junction: bool  # entry waypoint's is_junction (GlobalRoutePlanner's `intersection`)
    entry: Node
    exit: Node
    s: np.ndarray  # (n,) arc length from the entry

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def exit_vector(self) -> np.ndarray:
        return np.array([math.cos(self.yaw[-1]), math.sin(self.yaw[-1])])

    def net_vector(self) -> np.ndarray:
        d = self.xy[-1] - self.xy[0]
        n = float(np.hypot(*d))
        return d / n if n > 0 else np.zeros(2)


@dataclass(frozen=True)
class StopLine:
    """The stop line of a traffic light on one lane (yawil frame): centre, lane heading, lane width."""

    light_id: int
    x: float
    y: float
    yaw: float
    width: float = 3.5

    def ends(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The line across the lane: (left end, right end) seen in the direction of travel."""
        hx, hy = -math.sin(self.yaw) * self.width / 2, math.cos(self.yaw) * self.width / 2
        return (self.x + hx, self.y + hy), (self.x - hx, self.y - hy)


@dataclass(frozen=True)
class CarlaRoute:
    """A Route plus, per waypoint, the road and lane ids and the junction flag (for lane invasion)."""

    route: Route
    road: np.ndarray
    lane: np.ndarray
    junction: np.ndarray
    segments: tuple[int, ...]


def _node(x: float, y: float, z: float) -> Node:
    return (float(np.round(x)), float(np.round(y)), float(np.round(z)))


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _check_tuple(t: Any, where: str) -> WaypointTuple:
    if not isinstance(t, (list, tuple)) or len(t) != 7:
        raise ValueError(f"{where}: expected (x, y, z, yaw_deg, road_id, lane_id, is_junction), got {t!r}")
    x, y, z, yaw, road, lane, junc = t
    for name, v in (("x", x), ("y", y), ("z", z), ("yaw_deg", yaw)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise ValueError(f"{where}: {name} must be a finite number, got {v!r}")
    for name, v in (("road_id", road), ("lane_id", lane)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise ValueError(f"{where}: {name} must be an integer, got {v!r}")
    if lane == 0:
        raise ValueError(f"{where}: lane_id 0 is the reference line, not a driving lane")
    if not isinstance(junc, (bool, np.bool_)):
        raise ValueError(f"{where}: is_junction must be true or false, got {junc!r}")
    return (float(x), float(y), float(z), float(yaw), int(road), int(lane), bool(junc))


def _segment(points: Sequence[Any], where: str) -> Segment:
    """A segment from CARLA-frame tuples, densified (linear, heading unwrapped) to SAMPLING metres."""
    if not isinstance(points, (list, tuple)) or len(points) < 2:
        raise ValueError(f"{where}: a segment needs at least 2 waypoints, got {points!r:.80}")
    pts = [_check_tuple(p, f"{where}[{i}]") for i, p in enumerate(points)]
    xy = np.array([xy_from_carla(p[0], p[1]) for p in pts])
    z = np.array([p[2] for p in pts])
    yaw = np.unwrap(np.array([yaw_from_carla(p[3]) for p in pts]))
    road = np.array([p[4] for p in pts], dtype=np.int64)
    lane = np.array([p[5] for p in pts], dtype=np.int64)
    step = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(step)])
    if s[-1] <= 0.0:
        raise ValueError(f"{where}: segment has zero length (all waypoints at one place)")
    n_new = [max(1, math.ceil(d / SAMPLING - 1e-9)) for d in step]
    if max(n_new) > 1:
        s_new = np.concatenate([np.linspace(s[i], s[i + 1], k, endpoint=False) for i, k in enumerate(n_new)] + [s[-1:]])
        idx = np.clip(np.searchsorted(s, s_new, side="right") - 1, 0, len(s) - 1)
        xy = np.stack([np.interp(s_new, s, xy[:, 0]), np.interp(s_new, s, xy[:, 1])], axis=1)
        z, yaw, road, lane, s = np.interp(s_new, s, z), np.interp(s_new, s, yaw), road[idx], lane[idx], s_new
    yaw = np.array([wrap_angle(float(a)) for a in yaw])
    return Segment(xy, z, yaw, road, lane, pts[0][6], _node(pts[0][0], pts[0][1], pts[0][2]),
                   _node(pts[-1][0], pts[-1][1], pts[-1][2]), s)


class CarlaTopology:
    """The planner's graph of a CARLA map, with snapping, shortest routes and road options."""

    def __init__(self, segments: Sequence[Sequence[Any]], stops: Sequence[StopLine] = (), name: str = "") -> None:
        if not segments:
            raise ValueError(f"map {name!r}: the topology has no segments")
        self.name = name
        self.segments = [_segment(p, f"map {name!r} segment {i}") for i, p in enumerate(segments)]
        self.stops = tuple(stops)
        self.graph = nx.DiGraph()
        for i, seg in enumerate(self.segments):
            old = self.graph.get_edge_data(seg.entry, seg.exit)
            if old is None or self.segments[old["segment"]].length > seg.length:
                self.graph.add_edge(seg.entry, seg.exit, segment=i, length=seg.length)
        self._pts = np.concatenate([s.xy for s in self.segments])
        self._pts_yaw = np.concatenate([s.yaw for s in self.segments])
        self._pts_seg = np.concatenate([np.full(len(s.xy), i) for i, s in enumerate(self.segments)])
        self._pts_k = np.concatenate([np.arange(len(s.xy)) for s in self.segments])
        xy = self._pts
        self.bounds = (float(xy[:, 0].min()), float(xy[:, 1].min()), float(xy[:, 0].max()), float(xy[:, 1].max()))
        self._dist: dict[Node, dict[Node, float]] | None = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_json(cls, path: str | Path) -> CarlaTopology:
        """A recorded map description: {"format", "name", "segments": [[tuple, ...], ...], "lights": [...]}."""
        p = Path(path)
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            raise ValueError(f"{p}: cannot read a map description ({err})") from None
        if not isinstance(doc, dict) or doc.get("format") != MAP_FORMAT:
            raise ValueError(f"{p}: field 'format' must be {MAP_FORMAT!r}")
        segs = doc.get("segments")
        if not isinstance(segs, list):
            raise ValueError(f"{p}: field 'segments' must be a list of waypoint lists")
        stops: list[StopLine] = []
        for i, light in enumerate(doc.get("lights", [])):
            if not isinstance(light, dict) or not isinstance(light.get("id"), int) or not isinstance(light.get("stops"), list):
                raise ValueError(f"{p}: lights[{i}] must be {{'id': int, 'stops': [waypoint tuples]}}, got {light!r}")
            for j, t in enumerate(light["stops"]):
                x, y, _, yaw, *_ = _check_tuple(t, f"{p}: lights[{i}].stops[{j}]")
                stops.append(StopLine(light["id"], *xy_from_carla(x, y), yaw_from_carla(yaw), float(light.get("lane_width", 3.5))))
        return cls(segs, stops, name=str(doc.get("name", p.stem)))

    @classmethod
    def from_carla_map(cls, cmap: Any, lights: Sequence[Any] = (), resolution: float = SAMPLING) -> CarlaTopology:
        """From a carla.Map (and the world's carla.TrafficLight actors): GlobalRoutePlanner's sampling."""
        segments = [waypoint_path(a, b, resolution) for a, b in cmap.get_topology()]
        stops = [StopLine(int(tl.id), *xy_from_carla(w.transform.location.x, w.transform.location.y),
                          yaw_from_carla(w.transform.rotation.yaw), float(w.lane_width))
                 for tl in lights for w in tl.get_stop_waypoints()]
        return cls(segments, stops, name=str(cmap.name))

    # ------------------------------------------------------------------ queries
    def snap(self, pose: Pose) -> tuple[int, float, float]:
        """(segment, arc length on it, distance) of the nearest lane point heading within 90 deg of pose."""
        return self.snap_all(pose)[0]

    def snap_all(self, pose: Pose, tie: float = 0.05) -> list[tuple[int, float, float]]:
        """Every segment as near as the nearest (within `tie` m): CARLA's topology repeats a lane once per
        successor, so one place lies on several segments that end at different junction connectors."""
        ok = np.cos(self._pts_yaw - pose.yaw) > 0.0
        if not ok.any():
            raise ValueError(f"no lane of map {self.name!r} heads within 90 deg of {pose}")
        d2 = (self._pts[:, 0] - pose.x) ** 2 + (self._pts[:, 1] - pose.y) ** 2
        d2[~ok] = np.inf
        near = np.flatnonzero(d2 <= (math.sqrt(float(d2.min())) + 1.5) ** 2)
        best: dict[int, tuple[float, float]] = {}
        for j in near.tolist():
            i, k = int(self._pts_seg[j]), int(self._pts_k[j])
            seg = self.segments[i]
            for a in (k - 1, k):
                if 0 <= a < len(seg.xy) - 1:
                    p0, v = seg.xy[a], seg.xy[a + 1] - seg.xy[a]
                    t = float(np.clip(np.dot(np.array([pose.x, pose.y]) - p0, v) / max(float(np.dot(v, v)), 1e-12), 0.0, 1.0))
                    q = p0 + t * v
                    cand = (math.hypot(pose.x - q[0], pose.y - q[1]), float(seg.s[a] + t * (seg.s[a + 1] - seg.s[a])))
                    if i not in best or cand[0] < best[i][0]:
                        best[i] = cand
        dmin = min(d for d, _ in best.values())
        return sorted(((i, s, d) for i, (d, s) in best.items() if d <= dmin + tie), key=lambda c: (c[2], c[0]))

    def _path(self, s_seg: int, g_seg: int) -> list[int] | None:
        """Segments from s_seg to g_seg (both included) by the shortest path, None when unreachable."""
        a, b = self.segments[s_seg].exit, self.segments[g_seg].entry
        try:
            nodes = nx.dijkstra_path(self.graph, a, b, weight="length")
        except (nx.NetworkXNoPath, nx.NodeNotFound):
            return None
        return [s_seg] + [int(self.graph.edges[u, v]["segment"]) for u, v in zip(nodes, nodes[1:], strict=False)] + [g_seg]

    def plan(self, start: Pose, goal: Pose) -> CarlaRoute:
        """The shortest route between the snapped start and goal, sampled every metre, with road options."""
        best: tuple[float, list[int], float, float] | None = None
        dist = self.distances()
        for s_seg, s_s, _ in self.snap_all(start):
            for g_seg, g_s, _ in self.snap_all(goal):
                a, b = self.segments[s_seg], self.segments[g_seg]
                if s_seg == g_seg and g_s > s_s:
                    cand: tuple[float, list[int] | None] = (g_s - s_s, [s_seg])
                else:
                    cand = (a.length - s_s + dist.get(a.exit, {}).get(b.entry, math.inf) + g_s, None)
                if math.isfinite(cand[0]) and (best is None or cand[0] < best[0] - 1e-9):
                    seq = cand[1] if cand[1] is not None else self._path(s_seg, g_seg)
                    if seq is not None:
                        best = (cand[0], seq, s_s, g_s)
        if best is None:
            raise ValueError(f"goal {goal} is unreachable from start {start} on map {self.name!r}")
        return self.sample(best[1], best[2], best[3])

    def distances(self) -> dict[Node, dict[Node, float]]:
        if self._dist is None:
            self._dist = {k: dict(v) for k, v in nx.all_pairs_dijkstra_path_length(self.graph, weight="length")}
        return self._dist

    def random_route(self, rng: np.random.Generator, min_length: float = 0.0, max_tries: int = 5000,
                     start: Pose | None = None, goal: Pose | None = None) -> CarlaRoute:
        """A route between random points of non-junction segments (or the given ends), at least min_length."""
        dist = self.distances()
        roads = [i for i, s in enumerate(self.segments) if not s.junction and s.length > 2.0]
        if not roads:
            raise ValueError(f"map {self.name!r} has no road segment longer than 2 m")
        fixed_s = self.snap(start)[:2] if start is not None else None
        fixed_g = self.snap(goal)[:2] if goal is not None else None
        for _ in range(max_tries):
            ls, lg = (roads[int(i)] for i in rng.integers(0, len(roads), size=2))
            ss = float(rng.uniform(0.1, 0.6) * self.segments[ls].length)
            sg = float(rng.uniform(0.4, 0.9) * self.segments[lg].length)
            if fixed_s is not None:
                ls, ss = fixed_s
            if fixed_g is not None:
                lg, sg = fixed_g
            a, b = self.segments[ls], self.segments[lg]
            direct = ls == lg and sg > ss + 1.0
            between = dist.get(a.exit, {}).get(b.entry, math.inf)
            length = sg - ss if direct else a.length - ss + between + sg
            if not math.isfinite(length) or length < max(min_length, 1.0):
                continue
            seq = [ls] if direct else self._path(ls, lg)
            if seq is not None:
                return self.sample(seq, ss, sg)
        raise ValueError(f"no route of at least {min_length:.0f} m found on map {self.name!r} in {max_tries} draws")

    # ------------------------------------------------------------------ road options
    def turn_decisions(self, seq: Sequence[int]) -> list[RoadOption]:
        """GlobalRoutePlanner._turn_decision for each segment of the sequence."""
        out: list[RoadOption] = []
        previous = RoadOption.VOID
        end_node: Node | None = None
        for j, e in enumerate(seq):
            nxt = self.segments[e]
            if j == 0:
                decision = RoadOption.LANEFOLLOW
            else:
                cur = self.segments[seq[j - 1]]
                if previous is not RoadOption.VOID and end_node is not None and end_node != cur.entry and nxt.junction:
                    decision = previous
                else:
                    end_node = None
                    if not cur.junction and nxt.junction:
                        tail = nxt
                        for k in seq[j:]:
                            if not self.segments[k].junction:
                                break
                            tail, end_node = self.segments[k], self.segments[k].exit
                        decision = self._turn(cur, nxt, tail)
                    else:
                        decision = RoadOption.LANEFOLLOW
            previous = decision
            out.append(decision)
        return out

    def _turn(self, cur: Segment, nxt: Segment, tail: Segment) -> RoadOption:
        cv, nv = cur.exit_vector(), tail.exit_vector()
        others = [self.segments[int(d["segment"])] for _, v, d in self.graph.out_edges(cur.exit, data=True) if v != nxt.exit]
        crosses = [_cross(cv, o.net_vector()) for o in others] or [0.0]
        next_cross = _cross(cv, nv)
        deviation = math.acos(float(np.clip(np.dot(cv, nv), -1.0, 1.0)))
        if deviation < TURN_THRESHOLD:
            return RoadOption.STRAIGHT
        # yawil's frame is right-handed: a left turn has a positive cross product (CARLA's is negative)
        if next_cross > max(crosses):
            return RoadOption.LEFT
        if next_cross < min(crosses):
            return RoadOption.RIGHT
        return RoadOption.LEFT if next_cross > 0 else RoadOption.RIGHT

    # ------------------------------------------------------------------ sampling
    def sample(self, seq: Sequence[int], s_start: float, s_goal: float) -> CarlaRoute:
        """Dense route (every WAYPOINT_STEP metres) along a segment sequence from s_start to s_goal."""
        options = self.turn_decisions(seq)
        parts: list[tuple[np.ndarray, ...]] = []
        for j, e in enumerate(seq):
            seg = self.segments[e]
            lo = s_start if j == 0 else 0.0
            hi = s_goal if j == len(seq) - 1 else seg.length
            inner = (seg.s > lo) & (seg.s < hi)
            s_pts = np.concatenate([[lo], seg.s[inner], [hi]])
            xy = np.stack([np.interp(s_pts, seg.s, seg.xy[:, 0]), np.interp(s_pts, seg.s, seg.xy[:, 1])], axis=1)
            yaw = np.interp(s_pts, seg.s, np.unwrap(seg.yaw))
            k = np.clip(np.searchsorted(seg.s, s_pts, side="right") - 1, 0, len(seg.s) - 1)
            n = len(s_pts)
            parts.append((xy, yaw, seg.road[k], seg.lane[k], np.full(n, seg.junction), np.full(n, int(options[j]))))
        xy = np.concatenate([p[0] for p in parts])
        yaw_raw = np.concatenate([p[1] for p in parts])
        keep = np.concatenate([[True], np.hypot(*np.diff(xy, axis=0).T) > 1e-6])
        xy, yaw_raw = xy[keep], np.unwrap(yaw_raw[keep])
        road, lane, junc, opt = (np.concatenate([p[i] for p in parts])[keep] for i in range(2, 6))
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        total = float(cum[-1])
        if total < 1.0:
            raise ValueError(f"route is only {total:.2f} m long on map {self.name!r}; start and goal must be at least 1 m apart")
        d = stations(total)
        src = np.clip(np.searchsorted(cum, d, side="right") - 1, 0, len(cum) - 1)
        r_xy = np.stack([np.interp(d, cum, xy[:, 0]), np.interp(d, cum, xy[:, 1])], axis=1)
        r_yaw = np.array([wrap_angle(float(a)) for a in np.interp(d, cum, yaw_raw)])
        r_opt = opt[src].astype(np.int8)
        for i in np.flatnonzero(np.diff(r_opt.astype(np.int64), prepend=int(RoadOption.LANEFOLLOW)) != 0):
            if r_opt[i] == int(RoadOption.LANEFOLLOW):
                continue
            before = (d >= d[i] - PRE_JUNCTION) & (d < d[i]) & (r_opt == int(RoadOption.LANEFOLLOW))
            r_opt[before] = r_opt[i]
        r_junc = junc[src].astype(bool)
        route = Route(xy=r_xy, options=r_opt, lane_yaw=r_yaw, lights=self._route_lights(r_xy, r_yaw, r_junc))
        return CarlaRoute(route, road[src].astype(np.int64), lane[src].astype(np.int64), r_junc, tuple(int(e) for e in seq))

    def _route_lights(self, xy: np.ndarray, yaw: np.ndarray, junc: np.ndarray) -> tuple[tuple[int, int], ...]:
        """(waypoint index of the stop line, light id) of each light the route passes before a junction, and of
        one within GOAL_REACH past the goal (a car stopping at the goal crosses it; its index is the goal's)."""
        n = len(xy)
        reach = np.arange(WAYPOINT_STEP, GOAL_REACH + 1e-9, WAYPOINT_STEP)
        tail = xy[-1] + reach[:, None] * np.array([math.cos(yaw[-1]), math.sin(yaw[-1])])
        pts, hdg = np.vstack([xy, tail]), np.concatenate([yaw, np.full(len(reach), yaw[-1])])
        found: dict[int, int] = {}
        for stop in self.stops:
            near = np.hypot(pts[:, 0] - stop.x, pts[:, 1] - stop.y) <= STOP_MATCH_M
            near &= np.cos(hdg - stop.yaw) >= STOP_MATCH_COS
            idx = np.flatnonzero(near)
            if not len(idx):
                continue
            i = int(idx[np.argmin(np.hypot(pts[idx, 0] - stop.x, pts[idx, 1] - stop.y))])
            at_goal = i >= n - 1 - len(reach)
            if (junc[i + 1:].any() or at_goal) and stop.light_id not in found.values():
                found[min(i, n - 1)] = stop.light_id
        return tuple(sorted(found.items()))


def waypoint_path(a: Any, b: Any, resolution: float = SAMPLING) -> list[WaypointTuple]:
    """GlobalRoutePlanner._build_topology's dense path of one topology pair of carla.Waypoints, as tuples."""
    end = b.transform.location
    path = [a]
    w = a
    while True:
        nxt = w.next(resolution)
        if not nxt:
            break
        w = nxt[0]
        if w.transform.location.distance(end) <= resolution:
            break
        path.append(w)
        if len(path) > 100000:  # pragma: no cover - a malformed map
            raise ValueError(f"segment from road {a.road_id} lane {a.lane_id} does not reach its end")
    path.append(b)
    return [waypoint_tuple(p) for p in path]


def waypoint_tuple(w: Any) -> WaypointTuple:
    """A carla.Waypoint as the plain tuple of the map description (CARLA frame)."""
    loc, rot = w.transform.location, w.transform.rotation
    return (float(loc.x), float(loc.y), float(loc.z), float(rot.yaw), int(w.road_id), int(w.lane_id), bool(w.is_junction))


def write_map_description(topology_segments: Sequence[Sequence[WaypointTuple]], lights: Sequence[tuple[int, Sequence[WaypointTuple]]],
                          path: str | Path, name: str) -> None:
    """Record a map description (for tests and offline planning), written to a temporary file then renamed."""
    p = Path(path)
    doc = {"format": MAP_FORMAT, "name": name, "segments": [[list(t) for t in s] for s in topology_segments],
           "lights": [{"id": int(i), "stops": [list(t) for t in stops]} for i, stops in lights]}
    write_atomic(p, json.dumps(doc))
