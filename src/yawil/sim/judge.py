"""EpisodeJudge: the criteria of an episode, composed once for every backend.

A world builds one at reset from the route, its stop lines and the scenario, calls `start` with where the ego
stands, then `update` once a step with what its simulator knows (where the ego is, what it touches, the
lights); `update` returns the step's events in a fixed order (collision, lane invasion, light passed / red
light, goal, timeout) and sets `done` on the goal or the timeout. Adding a criterion is one line in
`EpisodeJudge.__init__`; the worlds do not change.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from yawil.sim.criteria import (
    CollisionCriterion,
    Contacts,
    Criterion,
    DistanceDrivenCriterion,
    GoalCriterion,
    LaneInvasionCriterion,
    RedLightCriterion,
    RouteProgressCriterion,
    StepState,
    TimeoutCriterion,
    nocrash_timeout,
)
from yawil.sim.types import Event, EventKind, Route, Scenario

# (light ids (S,), one end of each stop line (S, 2), the other end (S, 2), heading of the traffic it stops (S,))
StopLines = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
ENDING = (EventKind.GOAL_REACHED, EventKind.TIMEOUT)


class _NoContacts:
    def touching(self) -> set[tuple[str, int]]:
        return set()


NO_CONTACTS: Contacts = _NoContacts()


def episode_timeout(scenario: Scenario, route_length: float) -> float:
    """The scenario's own `timeout_s`, or NoCrash's budget for the route (`criteria.nocrash_timeout`)."""
    return float(scenario.timeout_s) if scenario.timeout_s is not None else nocrash_timeout(route_length)


class EpisodeJudge:
    """Every criterion of one episode. `progress` and `distance` are read by the worlds' observations."""

    def __init__(self, route: Route, stop_lines: StopLines, scenario: Scenario) -> None:
        self.timeout_s = episode_timeout(scenario, route.length)
        self.progress = RouteProgressCriterion(route.xy)
        self.collision = CollisionCriterion()
        self.lane = LaneInvasionCriterion()
        self.light = RedLightCriterion(*stop_lines)
        self.distance = DistanceDrivenCriterion()
        self.goal = GoalCriterion(route.xy)
        self.timeout = TimeoutCriterion(self.timeout_s)
        # the order of a step's events
        self.criteria: tuple[Criterion, ...] = (self.collision, self.lane, self.light, self.distance, self.goal,
                                                self.timeout)
        self.done = False

    def start(self, x: float, y: float, yaw: float, region: str) -> None:
        """A new episode with the ego at (x, y, yaw) in `region` (one of LaneInvasionCriterion.REGIONS)."""
        self.progress.reset()
        first = StepState(0.0, x, y, yaw, (x, y), 0, region, (), NO_CONTACTS)
        for c in self.criteria:
            c.start(first)
        self.done = False

    def update(self, time: float, x: float, y: float, yaw: float, prev_xy: tuple[float, float], contacts: Contacts,
               region: Callable[[int], str], light_states: Sequence[str]) -> list[Event]:
        """The events of the step that moved the ego from `prev_xy` to (x, y, yaw) at `time`.

        `region(route_index)` tells where the ego is, given its projection on the route this step (CARLA
        compares lanes with the route's); `light_states[i]` is the state of stop line i.
        """
        index = self.progress.update(x, y)
        state = StepState(time, x, y, yaw, prev_xy, index, region(index), light_states, contacts)
        events: list[Event] = []
        for c in self.criteria:
            events += c.judge(state)
        if any(e.kind in ENDING for e in events):
            self.done = True
        return events
