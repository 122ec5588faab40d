"""Infraction and progress criteria, one class per event (as CARLA scenario_runner does).

They take plain state (numbers and numpy arrays), not a simulator, so every backend reuses them: the
embedded world feeds them each step, a CARLA backend can feed them the same quantities. Each `update`
returns the events of that step; each criterion counts an infraction once per onset.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from yawil.sim.types import Event, EventKind


def nocrash_timeout(route_length: float) -> float:
    """NoCrash's time budget: (d/1000)/5*3600 + 20 s (5 km/h average plus 20 s)."""
    return route_length / 1000.0 / 5.0 * 3600.0 + 20.0


def boxes_overlap(ego: Sequence[float], boxes: np.ndarray) -> np.ndarray:
    """Separating-axis test of one oriented box (x, y, yaw, length, width) against K boxes (K, 5)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    x, y, yaw, length, width = (float(v) for v in ego)
    ca, sa = math.cos(yaw), math.sin(yaw)
    cb, sb = np.cos(boxes[:, 2]), np.sin(boxes[:, 2])
    dx, dy = boxes[:, 0] - x, boxes[:, 1] - y
    hl, hw = boxes[:, 3] / 2, boxes[:, 4] / 2
    separated = np.zeros(len(boxes), dtype=bool)
    # axes of the ego box (constant) then of each other box
    for ax, ay, ra_ego in ((ca, sa, length / 2), (-sa, ca, width / 2)):
        rb = hl * np.abs(cb * ax + sb * ay) + hw * np.abs(-sb * ax + cb * ay)
        separated |= np.abs(dx * ax + dy * ay) > ra_ego + rb
    for bx, by, rb_own in ((cb, sb, hl), (-sb, cb, hw)):
        ra = length / 2 * np.abs(ca * bx + sa * by) + width / 2 * np.abs(-sa * bx + ca * by)
        separated |= np.abs(dx * bx + dy * by) > ra + rb_own
    return ~separated


class CollisionCriterion:
    """A collision event each time the ego starts touching another actor or a static object."""

    def __init__(self) -> None:
        self._touching: set[tuple[str, int]] = set()

    def reset(self) -> None:
        self._touching = set()

    def update(self, time: float, ego: Sequence[float], boxes: np.ndarray, ids: np.ndarray,
               types: Sequence[str]) -> list[Event]:
        """`boxes` (K, 5) of candidates, their `ids` and `types` ("vehicle", "pedestrian", "static")."""
        hit = boxes_overlap(ego, boxes) if len(boxes) else np.zeros(0, dtype=bool)
        now = {(types[i], int(ids[i])) for i in np.flatnonzero(hit).tolist()}
        events = [
            Event(EventKind.COLLISION, time, float(ego[0]), float(ego[1]),
                  other_id=None if kind == "static" else oid, other_type=kind)
            for kind, oid in sorted(now - self._touching)
        ]
        self._touching = now
        return events


class LaneInvasionCriterion:
    """Entering the opposite-direction lane or leaving the road, counted once per entry.

    The backend classifies where the ego is: "lane" (its own direction), "opposite_lane", "junction"
    (no direction inside junctions) or "off_road".
    """

    REGIONS = ("lane", "opposite_lane", "junction", "off_road")

    def __init__(self) -> None:
        self._last = "lane"

    def reset(self, region: str = "lane") -> None:
        self._last = region

    def update(self, time: float, x: float, y: float, region: str) -> list[Event]:
        if region not in self.REGIONS:
            raise ValueError(f"unknown region {region!r}; expected one of {self.REGIONS}")
        events = []
        if region in ("opposite_lane", "off_road") and region != self._last:
            events.append(Event(EventKind.LANE_INVASION, time, x, y, detail=region))
        self._last = region
        return events


class RedLightCriterion:
    """Crossing a signalised stop line (the ego's centre moving over it, in its direction of travel).

    Every crossing is a LIGHT_PASSED event; when the light is red it is also a RED_LIGHT event.
    """

    def __init__(self, ids: np.ndarray, centre: np.ndarray, kerb: np.ndarray, yaw: np.ndarray) -> None:
        self.ids = np.asarray(ids, dtype=np.int64)
        self.a = np.asarray(centre, dtype=np.float64).reshape(-1, 2)
        self.b = np.asarray(kerb, dtype=np.float64).reshape(-1, 2)
        self.yaw = np.asarray(yaw, dtype=np.float64)
        self.mid = 0.5 * (self.a + self.b)
        self.reach = 0.5 * np.hypot(*(self.b - self.a).T) + 1.0

    def reset(self) -> None:
        pass

    def update(self, time: float, prev_xy: Sequence[float], xy: Sequence[float], yaw: float,
               states: Sequence[str]) -> list[Event]:
        """`states[i]` is the state name ("red", "yellow", "green") of light `ids[i]`."""
        if not len(self.ids):
            return []
        px, py = float(prev_xy[0]), float(prev_xy[1])
        qx, qy = float(xy[0]), float(xy[1])
        step = math.hypot(qx - px, qy - py)
        near = np.hypot(self.mid[:, 0] - qx, self.mid[:, 1] - qy) <= self.reach + step
        events: list[Event] = []
        for i in np.flatnonzero(near).tolist():
            if math.cos(yaw - self.yaw[i]) <= 0.0:
                continue
            if _segments_cross((px, py), (qx, qy), self.a[i], self.b[i]):
                lid = int(self.ids[i])
                events.append(Event(EventKind.LIGHT_PASSED, time, qx, qy, other_id=lid, detail=states[i]))
                if states[i] == "red":
                    events.append(Event(EventKind.RED_LIGHT, time, qx, qy, other_id=lid, detail="red"))
        return events


def _segments_cross(p: Sequence[float], q: Sequence[float], a: Sequence[float], b: Sequence[float]) -> bool:
    """Proper or touching intersection of segments pq and ab, where q may end on the line but p may not."""

    def orient(o: Sequence[float], s: Sequence[float], t: Sequence[float]) -> float:
        return (s[0] - o[0]) * (t[1] - o[1]) - (s[1] - o[1]) * (t[0] - o[0])

    d1, d2 = orient(a, b, p), orient(a, b, q)
    d3, d4 = orient(p, q, a), orient(p, q, b)
    return d1 != 0 and (d2 == 0 or (d1 > 0) != (d2 > 0)) and d3 * d4 <= 0


class RouteProgressCriterion:
    """The ego's projection on the route (searched near the last one, so loops do not confuse it)."""

    def __init__(self, route_xy: np.ndarray, back: int = 5, ahead: int = 40) -> None:
        self.xy = np.asarray(route_xy, dtype=np.float64)
        self.back, self.ahead = back, ahead
        self.index = 0
        self.max_index = 0

    def reset(self) -> None:
        self.index = self.max_index = 0

    def update(self, x: float, y: float) -> int:
        lo = max(0, self.index - self.back)
        hi = min(len(self.xy), self.index + self.ahead + 1)
        seg = self.xy[lo:hi]
        self.index = lo + int(np.argmin((seg[:, 0] - x) ** 2 + (seg[:, 1] - y) ** 2))
        self.max_index = max(self.max_index, self.index)
        return self.index

    @property
    def progress(self) -> float:
        """Metres of route covered (furthest projection so far)."""
        d = np.hypot(*np.diff(self.xy[: self.max_index + 1], axis=0).T)
        return float(d.sum())


class DistanceDrivenCriterion:
    def __init__(self) -> None:
        self.total = 0.0

    def reset(self) -> None:
        self.total = 0.0

    def update(self, prev_xy: Sequence[float], xy: Sequence[float]) -> float:
        self.total += math.hypot(float(xy[0]) - float(prev_xy[0]), float(xy[1]) - float(prev_xy[1]))
        return self.total


GOAL_WINDOW = 10  # waypoints (about metres): the goal counts once route progress is this close to the end


class GoalCriterion:
    """Goal reached: within `radius` metres of the route's last waypoint, near the end of the route.

    With `last_index` (the route's last waypoint index) the ego's route progress must also be within
    `window` waypoints of it: a route that loops back past its own start (town02 navigation 13 ends 0.4 m
    from where it begins) is otherwise "reached" on its first step.
    """

    def __init__(self, goal_xy: Sequence[float], radius: float = 2.0, last_index: int | None = None,
                 window: int = GOAL_WINDOW) -> None:
        self.goal = (float(goal_xy[0]), float(goal_xy[1]))
        self.radius = radius
        self.first_index = None if last_index is None else max(last_index - window, 0)
        self.reached = False

    def reset(self) -> None:
        self.reached = False

    def update(self, time: float, x: float, y: float, progress_index: int | None = None) -> list[Event]:
        if self.first_index is not None and (progress_index is None or progress_index < self.first_index):
            return []
        if not self.reached and math.hypot(x - self.goal[0], y - self.goal[1]) <= self.radius:
            self.reached = True
            return [Event(EventKind.GOAL_REACHED, time, x, y)]
        return []


class TimeoutCriterion:
    def __init__(self, timeout_s: float) -> None:
        if not math.isfinite(timeout_s) or timeout_s <= 0:
            raise ValueError(f"timeout_s must be a positive number of seconds, got {timeout_s!r}")
        self.timeout = timeout_s
        self.expired = False

    def reset(self) -> None:
        self.expired = False

    def update(self, time: float, x: float, y: float) -> list[Event]:
        if not self.expired and time >= self.timeout - 1e-9:
            self.expired = True
            return [Event(EventKind.TIMEOUT, time, x, y)]
        return []
