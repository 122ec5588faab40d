"""The lane graph: one lane per direction on each road, plus a connector lane per allowed manoeuvre.

Every lane is a cubic Bezier curve (straight roads are degenerate ones), so position and heading are known
analytically at any arc length; the heading reported to the planner (Route.lane_yaw) is the curve's own
tangent, never a difference of waypoints. Traffic is right-hand (as CARLA): the lane from node a to node b
lies to the right of the road's centre line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from yawil.sim.town.map.layout import Layout, setback
from yawil.sim.types import RoadOption, wrap_angle

SAMPLE_STEP = 0.5  # metres between the precomputed lane samples used for vectorised lookups
STRAIGHT_TOLERANCE = math.radians(30.0)


def bezier_handle(p0: np.ndarray, h0: float, p3: np.ndarray, h1: float) -> float:
    """Handle length that makes a cubic Bezier approximate the circular arc between two headings."""
    chord = float(np.hypot(*(p3 - p0)))
    phi = abs(wrap_angle(h1 - h0))
    if phi < 1e-6:
        return chord / 3.0
    radius = chord / (2.0 * math.sin(phi / 2.0))
    return 4.0 / 3.0 * math.tan(phi / 4.0) * radius


@dataclass
class Lane:
    id: int
    kind: str  # "road" | "connector"
    ctrl: np.ndarray  # (4, 2) Bezier control points
    option: RoadOption
    road: int = -1  # road index (road lanes)
    node: int = -1  # node index (connectors)
    start_node: int = -1
    end_node: int = -1
    entry: int = -1  # connectors: the incoming road lane
    exit: int = -1  # connectors: the outgoing road lane
    successors: list[int] = field(default_factory=list)
    _t: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    _s: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def __post_init__(self) -> None:
        t = np.linspace(0.0, 1.0, 257)
        xy = self._point(t)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        self._t, self._s = t, s

    @property
    def length(self) -> float:
        return float(self._s[-1])

    def _point(self, t: np.ndarray) -> np.ndarray:
        c = self.ctrl
        u = 1.0 - t
        return ((u**3)[:, None] * c[0] + (3 * u * u * t)[:, None] * c[1] + (3 * u * t * t)[:, None] * c[2]
                + (t**3)[:, None] * c[3])

    def evaluate(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(xy (N, 2), yaw (N,)) at arc lengths s; yaw from the analytic tangent."""
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        t = np.interp(s, self._s, self._t)
        c = self.ctrl
        u = 1.0 - t
        d = ((3 * u * u)[:, None] * (c[1] - c[0]) + (6 * u * t)[:, None] * (c[2] - c[1])
             + (3 * t * t)[:, None] * (c[3] - c[2]))
        return self._point(t), np.arctan2(d[:, 1], d[:, 0])


@dataclass(frozen=True)
class Approach:
    """A signalised junction entry: the road lane, its stop line and the light governing it."""

    light: int
    lane: int
    node: int
    stop_s: float  # arc length of the stop line on the lane
    stop_xy: tuple[float, float]
    yaw: float
    kerb_xy: tuple[float, float]  # the stop line's end at the kerb (the other end is stop_xy's mirror on the centre line)
    centre_xy: tuple[float, float]  # the stop line's end at the road centre line


class LaneGraph:
    """Lanes, connectors and the tables traffic and planner look things up in."""

    STOP_BACK = 4.0  # stop line this far before the junction (a crosswalk lies between)
    CROSSWALK = (0.5, 3.5)  # crosswalk band, metres before the junction entry

    def __init__(self, layout: Layout) -> None:
        self.layout = layout
        self.lanes: list[Lane] = []
        nodes = np.array([(x, y) for _, x, y in layout.nodes])
        self.node_xy = nodes
        self.degree = np.array([layout.degree(i) for i in range(len(nodes))])
        half = layout.lane_width / 2.0
        # road lanes
        self.road_lanes: list[tuple[int, int]] = []  # per road: (lane a->b, lane b->a)
        for r, (a, b) in enumerate(layout.roads):
            ids = []
            for p, q in ((a, b), (b, a)):
                u = (nodes[q] - nodes[p]) / np.linalg.norm(nodes[q] - nodes[p])
                right = np.array([u[1], -u[0]])
                p0 = nodes[p] + u * setback(layout, p) + right * half
                p1 = nodes[q] - u * setback(layout, q) + right * half
                ctrl = np.array([p0, p0 + (p1 - p0) / 3, p0 + 2 * (p1 - p0) / 3, p1])
                lane = Lane(len(self.lanes), "road", ctrl, RoadOption.LANEFOLLOW, road=r, start_node=p, end_node=q)
                self.lanes.append(lane)
                ids.append(lane.id)
            self.road_lanes.append((ids[0], ids[1]))
        self.n_road_lanes = len(self.lanes)
        # connectors: every incoming lane to every outgoing lane of another road (no U-turns)
        self.node_connectors: dict[int, list[int]] = {i: [] for i in range(len(nodes))}
        for node in range(len(nodes)):
            incoming = [ln for ln in self.lanes[: self.n_road_lanes] if ln.end_node == node]
            outgoing = [ln for ln in self.lanes[: self.n_road_lanes] if ln.start_node == node]
            for li in incoming:
                for lo in outgoing:
                    if lo.road == li.road:
                        continue
                    p0, h0 = self._end(li)
                    p3, h1 = self._start(lo)
                    k = bezier_handle(p0, h0, p3, h1)
                    ctrl = np.array([p0, p0 + k * np.array([math.cos(h0), math.sin(h0)]),
                                     p3 - k * np.array([math.cos(h1), math.sin(h1)]), p3])
                    turn = wrap_angle(h1 - h0)
                    if self.degree[node] == 2:
                        option = RoadOption.LANEFOLLOW
                    elif abs(turn) < STRAIGHT_TOLERANCE:
                        option = RoadOption.STRAIGHT
                    else:
                        option = RoadOption.LEFT if turn > 0 else RoadOption.RIGHT
                    c = Lane(len(self.lanes), "connector", ctrl, option, node=node, start_node=node, end_node=node,
                             entry=li.id, exit=lo.id)
                    self.lanes.append(c)
                    li.successors.append(c.id)
                    c.successors.append(lo.id)
                    self.node_connectors[node].append(c.id)
        self.length = np.array([ln.length for ln in self.lanes])
        self._build_samples()
        self._build_conflicts()
        self._build_approaches()

    @staticmethod
    def _end(lane: Lane) -> tuple[np.ndarray, float]:
        xy, yaw = lane.evaluate(np.array([lane.length]))
        return xy[0], float(yaw[0])

    @staticmethod
    def _start(lane: Lane) -> tuple[np.ndarray, float]:
        xy, yaw = lane.evaluate(np.array([0.0]))
        return xy[0], float(yaw[0])

    def is_junction(self, node: int) -> bool:
        return bool(self.degree[node] >= 3)

    def _build_samples(self) -> None:
        pts, yaws, lane_of, s_of, offset, step = [], [], [], [], [], []
        n = 0
        for ln in self.lanes:
            count = max(2, int(math.ceil(ln.length / SAMPLE_STEP)) + 1)
            s = np.linspace(0.0, ln.length, count)
            xy, yaw = ln.evaluate(s)
            pts.append(xy)
            yaws.append(yaw)
            lane_of.append(np.full(count, ln.id))
            s_of.append(s)
            offset.append(n)
            step.append(ln.length / (count - 1))
            n += count
        self.sample_xy = np.concatenate(pts)
        self.sample_yaw = np.concatenate(yaws)
        self.sample_lane = np.concatenate(lane_of)
        self.sample_s = np.concatenate(s_of)
        self.sample_offset = np.array(offset)
        self.sample_count = np.array([len(p) for p in pts])
        self.sample_step = np.array(step)

    def lookup(self, lane: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vectorised (x, y, yaw) at (lane, s) from the precomputed samples, linear in between."""
        f = np.clip(s, 0.0, self.length[lane]) / self.sample_step[lane]
        i0 = np.minimum(f.astype(np.int64), self.sample_count[lane] - 2)
        w = f - i0
        j = self.sample_offset[lane] + i0
        p0, p1 = self.sample_xy[j], self.sample_xy[j + 1]
        x = p0[:, 0] + (p1[:, 0] - p0[:, 0]) * w
        y = p0[:, 1] + (p1[:, 1] - p0[:, 1]) * w
        return x, y, self.sample_yaw[j + np.rint(w).astype(np.int64)]

    def snap(self, x: float, y: float, yaw: float | None = None, roads_only: bool = False) -> tuple[int, float, float]:
        """Nearest (lane, s, distance) whose heading is within 90 degrees of yaw (any heading if yaw is None)."""
        d2 = (self.sample_xy[:, 0] - x) ** 2 + (self.sample_xy[:, 1] - y) ** 2
        mask = np.ones(len(d2), dtype=bool)
        if yaw is not None:
            mask &= np.cos(self.sample_yaw - yaw) > 0.0
        if roads_only:
            mask &= self.sample_lane < self.n_road_lanes
        d2 = np.where(mask, d2, np.inf)
        i = int(np.argmin(d2))
        return int(self.sample_lane[i]), float(self.sample_s[i]), float(math.sqrt(d2[i]))

    def _build_conflicts(self) -> None:
        """Connector pairs of one junction that cross or merge (different entries): they cannot be shared."""
        n = len(self.lanes)
        self.conflict = np.zeros((n, n), dtype=bool)
        for node, conns in self.node_connectors.items():
            if self.degree[node] < 3:
                continue
            for i in conns:
                for j in conns:
                    a, b = self.lanes[i], self.lanes[j]
                    if i >= j or a.entry == b.entry:
                        continue
                    pa = self.sample_xy[self.sample_lane == i]
                    pb = self.sample_xy[self.sample_lane == j]
                    dmin = np.min(np.hypot(pa[:, None, 0] - pb[None, :, 0], pa[:, None, 1] - pb[None, :, 1]))
                    if a.exit == b.exit or dmin < 2.5:
                        self.conflict[i, j] = self.conflict[j, i] = True

    def _build_approaches(self) -> None:
        self.approaches: list[Approach] = []
        self.light_of_lane = np.full(len(self.lanes), -1, dtype=np.int64)
        if not self.layout.signalised:
            return
        half = self.layout.lane_width / 2.0
        for ln in self.lanes[: self.n_road_lanes]:
            if not self.is_junction(ln.end_node):
                continue
            stop_s = ln.length - self.STOP_BACK
            xy, yaw = ln.evaluate(np.array([stop_s]))
            right = np.array([math.sin(yaw[0]), -math.cos(yaw[0])])
            kerb = xy[0] + right * half
            centre = xy[0] - right * half
            a = Approach(len(self.approaches), ln.id, ln.end_node, float(stop_s), (float(xy[0, 0]), float(xy[0, 1])),
                         float(yaw[0]), (float(kerb[0]), float(kerb[1])), (float(centre[0]), float(centre[1])))
            self.light_of_lane[ln.id] = a.light
            self.approaches.append(a)
