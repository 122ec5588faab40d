"""Infraction and progress criteria, one class per event (as CARLA scenario_runner's `atomic_criteria.py`).

Every criterion is a `Criterion`: `start(first)` when an episode begins, `judge(state)` once a step, which
returns the events of that step; each counts an infraction once per onset. `state` is a `StepState`, plain
numbers and arrays that each backend fills from its own simulator, so every backend runs the same rules.
`yawil.sim.judge.EpisodeJudge` composes them once for both worlds. Each criterion also keeps its rule as a
method on plain numbers (`update(...)`), for callers outside an episode (the benchmark's tracker, tests).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from yawil.sim.types import Event, EventKind


class Contacts(Protocol):
    """What the ego touches this step, as each backend knows it (boxes, a collision sensor)."""

    def touching(self) -> set[tuple[str, int]]:
        """(kind, id) of everything in contact: kind "vehicle" | "pedestrian" | "static"."""
        ...


@dataclass(frozen=True)
class StepState:
    """What the criteria see of one step (the step's end; `prev_xy` is the ego's position before it)."""

    time: float
    x: float
    y: float
    yaw: float
    prev_xy: tuple[float, float]
    route_index: int  # the ego's projection on the route (RouteProgressCriterion), this step
    region: str  # where the ego is: one of LaneInvasionCriterion.REGIONS
    light_states: Sequence[str]  # the state name of each stop line the judge was built with
    contacts: Contacts


class Criterion(abc.ABC):
    """One rule of an episode. Subclasses implement `judge`; `start` resets them (override if it needs `first`)."""

    def reset(self) -> None:  # noqa: B027 (a hook, not abstract: a rule with no state keeps this one)
        """Forget the previous episode."""

    def start(self, first: StepState) -> None:
        """A new episode begins at `first` (nothing is judged on it)."""
        self.reset()

    @abc.abstractmethod
    def judge(self, state: StepState) -> list[Event]:
        """The events of the step that ends in `state`."""


def nocrash_timeout(route_length: float) -> float:
    """NoCrash's time budget: (d/1000)/5*3600 + 20 s (5 km/h average plus 20 s)."""
    return route_length / 1000.0 / 5.0 * 3600.0 + 20.0


def corl2017_timeout(route_length: float) -> float:
    """CoRL2017's time budget: (d/1000)/10*3600 + 10 s (10 km/h average plus 10 s; coiltraine's
    driving-benchmarks `_calculate_time_out`). Always shorter than NoCrash's for the same route."""
    return route_length / 1000.0 / 10.0 * 3600.0 + 10.0


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


@dataclass(frozen=True)
class BoxContacts:
    """Contacts by oriented boxes: the ego's (x, y, yaw, length, width) against candidates (K, 5)."""

    ego: Sequence[float]
    boxes: np.ndarray
    ids: np.ndarray
    types: Sequence[str]  # "vehicle" | "pedestrian" | "static" of each candidate

    def touching(self) -> set[tuple[str, int]]:
        hit = boxes_overlap(self.ego, self.boxes) if len(self.boxes) else np.zeros(0, dtype=bool)
        return {(self.types[i], int(self.ids[i])) for i in np.flatnonzero(hit).tolist()}


class CollisionCriterion(Criterion):
    """A collision event each time the ego starts touching another actor or a static object."""

    def __init__(self) -> None:
        self._touching: set[tuple[str, int]] = set()

    def reset(self) -> None:
        self._touching = set()

    def update(self, time: float, x: float, y: float, contacts: Contacts) -> list[Event]:
        """One event per (kind, id) in `contacts` that was not touching on the previous step."""
        now = contacts.touching()
        events = [
            Event(EventKind.COLLISION, time, float(x), float(y), other_id=None if kind == "static" else oid,
                  other_type=kind)
            for kind, oid in sorted(now - self._touching)
        ]
        self._touching = now
        return events

    def judge(self, state: StepState) -> list[Event]:
        return self.update(state.time, state.x, state.y, state.contacts)


class LaneInvasionCriterion(Criterion):
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

    def start(self, first: StepState) -> None:
        self.reset(first.region)

    def judge(self, state: StepState) -> list[Event]:
        return self.update(state.time, state.x, state.y, state.region)


class RedLightCriterion(Criterion):
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

    def judge(self, state: StepState) -> list[Event]:
        return self.update(state.time, state.prev_xy, (state.x, state.y), state.yaw, state.light_states)


def _segments_cross(p: Sequence[float], q: Sequence[float], a: Sequence[float], b: Sequence[float]) -> bool:
    """Proper or touching intersection of segments pq and ab, where q may end on the line but p may not."""

    def orient(o: Sequence[float], s: Sequence[float], t: Sequence[float]) -> float:
        return (s[0] - o[0]) * (t[1] - o[1]) - (s[1] - o[1]) * (t[0] - o[0])

    d1, d2 = orient(a, b, p), orient(a, b, q)
    d3, d4 = orient(p, q, a), orient(p, q, b)
    return d1 != 0 and (d2 == 0 or (d1 > 0) != (d2 > 0)) and d3 * d4 <= 0


class RouteProgressCriterion:
    """The ego's projection on the route (searched near the last one, so loops do not confuse it).

    A measurement, not a `Criterion`: it gives no events, and its index is the other criteria's input
    (`StepState.route_index`), so the judge takes it first each step.
    """

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


class DistanceDrivenCriterion(Criterion):
    """Metres driven since the start (`total`); no events."""

    def __init__(self) -> None:
        self.total = 0.0

    def reset(self) -> None:
        self.total = 0.0

    def update(self, prev_xy: Sequence[float], xy: Sequence[float]) -> float:
        self.total += math.hypot(float(xy[0]) - float(prev_xy[0]), float(xy[1]) - float(prev_xy[1]))
        return self.total

    def judge(self, state: StepState) -> list[Event]:
        self.update(state.prev_xy, (state.x, state.y))
        return []


GOAL_RADIUS = 2.0  # metres from the route's last waypoint
GOAL_ROUTE_LEFT = 10.0  # metres of route at most still ahead of the ego's projection on it


def _route_array(route_xy: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
    xy = np.asarray(route_xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) == 0:
        raise ValueError(f"route_xy must be an (N, 2) array of waypoints with N >= 1, got shape {xy.shape}")
    return xy


def route_left_table(route_xy: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
    """Metres of route from each waypoint to the last, (N,): computed once per route, a lookup per step."""
    xy = _route_array(route_xy)
    seg = np.hypot(*np.diff(xy, axis=0).T)
    return np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])


def _check_index(index: int, n: int) -> int:
    i = int(index)
    if not 0 <= i < n:
        raise ValueError(f"route index {index!r} is outside the route's {n} waypoints (0..{n - 1})")
    return i


def route_left(route_xy: np.ndarray | Sequence[Sequence[float]], index: int) -> float:
    """Metres of route still ahead of waypoint `index` (the ego's projection on the route)."""
    table = route_left_table(route_xy)
    return float(table[_check_index(index, len(table))])


def goal_reached(x: float, y: float, route_xy: np.ndarray | Sequence[Sequence[float]], index: int,
                 left: np.ndarray | None = None) -> bool:
    """The one goal rule of the project (worlds' `done` and the benchmark's success).

    Within `GOAL_RADIUS` metres of the route's last waypoint with at most `GOAL_ROUTE_LEFT` metres of route
    ahead of waypoint `index`. The second part measures metres, not waypoints, so it holds for any waypoint
    spacing; it keeps a route that loops back past its own start (town02 navigation 13 ends 0.4 m from where
    it begins) from being reached on its first step. `left` is `route_left_table(route_xy)`, passed by
    callers that judge every step so that the radius test plus one lookup is all a step costs.
    """
    xy = _route_array(route_xy)
    i = _check_index(index, len(xy))
    if math.hypot(float(x) - float(xy[-1, 0]), float(y) - float(xy[-1, 1])) > GOAL_RADIUS:
        return False
    if left is None:
        left = route_left_table(xy)
    elif len(left) != len(xy):
        raise ValueError(f"left has {len(left)} entries for a route of {len(xy)} waypoints; "
                         "expected route_left_table(route_xy)")
    return float(left[i]) <= GOAL_ROUTE_LEFT


class GoalCriterion(Criterion):
    """A goal_reached event, once, the first step `goal_reached` holds (the route's table built once)."""

    def __init__(self, route_xy: np.ndarray | Sequence[Sequence[float]]) -> None:
        self.xy = _route_array(route_xy)
        self.left = route_left_table(self.xy)
        self.reached = False

    def reset(self) -> None:
        self.reached = False

    def update(self, time: float, x: float, y: float, index: int) -> list[Event]:
        """`index` is the ego's projection on the route this step (the observation's `route_index`)."""
        if not self.reached and goal_reached(x, y, self.xy, index, self.left):
            self.reached = True
            return [Event(EventKind.GOAL_REACHED, time, x, y)]
        return []

    def judge(self, state: StepState) -> list[Event]:
        return self.update(state.time, state.x, state.y, state.route_index)


class TimeoutCriterion(Criterion):
    """A timeout event, once, when the episode's time reaches `timeout_s`."""

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

    def judge(self, state: StepState) -> list[Event]:
        return self.update(state.time, state.x, state.y)
