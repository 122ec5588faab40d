"""The embedded world's goal: reached at the end of the route, not where a loop route passes its goal."""

from __future__ import annotations

from yawil.sim import Control, EventKind, Scenario
from yawil.sim.town.world import EmbeddedWorld


def test_a_loop_route_whose_goal_lies_behind_its_start_is_not_done_at_once() -> None:
    """benchmarks/expert.py town02 seed 23: a 332 m loop ending 0.1 m behind its start was 'reached' in one step."""
    w = EmbeddedWorld()
    obs = w.reset(Scenario(town="town02", vehicles=0, pedestrians=0, camera=False, min_route_length=300.0), seed=23)
    route = obs.route
    assert route.length > 300.0 and abs(route.xy[0] - route.xy[-1]).max() < 2.0  # the loop
    for _ in range(20):
        obs = w.step(Control(brake=1.0))
        assert not obs.done and EventKind.GOAL_REACHED not in [e.kind for e in obs.events]
