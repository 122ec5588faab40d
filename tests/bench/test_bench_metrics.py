"""Episode judging and the Table III/IV aggregates on synthetic observations and records."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from yawil.bench.metrics import (
    EpisodeTracker,
    best_of,
    failure_counts,
    lane_violations_per_km,
    light_violation_ratio,
    mean_std,
    success_rate,
    task_success,
    task_violations,
    timeout_for,
)
from yawil.sim.criteria import GoalCriterion
from yawil.sim.types import Event, EventKind, Observation, Pose, RoadOption, Route


def _obs(x: float, y: float = 0.0, events: tuple[Event, ...] = (), done: bool = False, dist: float = 0.0) -> Observation:
    xy = np.stack([np.arange(0, 101, 1.0), np.zeros(101)], axis=1)
    route = Route(xy=xy, options=np.full(101, 4, np.int8), lane_yaw=np.zeros(101))
    return Observation(
        image=None, speed=5.0, pose=Pose(x, y, 0.0), route=route, route_index=int(np.clip(round(x), 0, 100)),
        command=RoadOption.LANEFOLLOW,
        events=events, time=0.0, frame=0, done=done, distance_driven=dist, town="t", bounds=(0, 0, 100, 10),
        weather="ClearNoon",
    )


def _rec(seed: int, success: bool, km: float = 1.0, opp: int = 0, off: int = 0, red: int = 0, passed: int = 0,
         task: str = "regular", reason: str | None = None) -> dict:
    return {"task": task, "condition": "training", "seed": seed, "route_id": 0, "success": success,
            "km_driven": km, "lane_opposite": opp, "lane_offroad": off, "red_lights": red,
            "lights_passed": passed, "reason": None if success else (reason or "timeout")}


def test_timeout_formula_is_nocrash() -> None:
    assert timeout_for(1000.0) == pytest.approx(720.0 + 20.0)
    assert timeout_for(0.0) == 20.0
    with pytest.raises(ValueError, match="route length"):
        timeout_for(-1.0)


def test_success_within_two_metres() -> None:
    tr = EpisodeTracker(goal_xy=(100.0, 0.0), timeout_s=60.0)
    tr.start(_obs(0.0))
    assert not tr.update(_obs(50.0, dist=50.0))
    assert not tr.update(_obs(97.9, dist=97.9))  # 2.1 m away: not yet
    assert tr.update(_obs(98.1, dist=98.1))
    res = tr.result()
    assert res["success"] and res["reason"] is None and res["steps"] == 3
    assert res["km_driven"] == pytest.approx(0.0981)
    assert res["trajectory"][0] == [0.0, 0.0] and res["trajectory"][-1] == [98.1, 0.0]


def test_goal_of_a_looping_route_counts_only_at_its_end() -> None:
    """A route that ends where it starts (town02 navigation 13) is not reached on the first step."""
    t = np.linspace(0.0, 2 * np.pi, 400)
    xy = np.stack([30.0 * np.sin(t), 30.0 * (1.0 - np.cos(t))], axis=1)  # a 188 m loop, end == start
    route = Route(xy=xy, options=np.full(len(xy), 4, np.int8), lane_yaw=np.zeros(len(xy)))

    def at(i: int) -> Observation:
        return Observation(
            image=None, speed=5.0, pose=Pose(float(xy[i, 0]), float(xy[i, 1]), 0.0), route=route, route_index=i,
            command=RoadOption.LANEFOLLOW, events=(), time=0.0, frame=0, done=False, distance_driven=0.0,
            town="t", bounds=(-40, -10, 40, 70), weather="ClearNoon",
        )  # fmt: skip

    tr = EpisodeTracker(goal_xy=(float(xy[-1, 0]), float(xy[-1, 1])), timeout_s=600.0)
    tr.start(at(0))
    assert not tr.update(at(1))  # 0.5 m from the goal, but the whole loop is still ahead
    assert not tr.update(at(200))
    assert tr.update(at(398)) and tr.result()["success"]


def test_success_measures_metres_of_route_left_and_agrees_with_the_world() -> None:
    """5 m waypoints (a CARLA planner's spacing): the goal needs <= 10 m of route left, not 10 waypoints."""
    xy = np.stack([np.arange(0.0, 101.0, 5.0), np.zeros(21)], axis=1)
    route = Route(xy=xy, options=np.full(21, 4, np.int8), lane_yaw=np.zeros(21))

    def at(x: float, i: int) -> Observation:
        return Observation(
            image=None, speed=5.0, pose=Pose(x, 0.0, 0.0), route=route, route_index=i,
            command=RoadOption.LANEFOLLOW, events=(), time=0.0, frame=0, done=False, distance_driven=0.0,
            town="t", bounds=(0, -10, 100, 10), weather="ClearNoon",
        )  # fmt: skip

    tr = EpisodeTracker(goal_xy=(100.0, 0.0), timeout_s=600.0)
    world_rule = GoalCriterion(xy)
    tr.start(at(0.0, 0))
    for i in (10, 17):  # at the goal, but 50 m and 15 m of route still ahead of the projection
        assert not tr.update(at(100.0, i)) and world_rule.update(0.1, 100.0, 0.0, i) == []
    assert tr.update(at(100.0, 18)) and tr.result()["success"]
    assert len(world_rule.update(0.2, 100.0, 0.0, 18)) == 1


def test_goal_must_be_the_routes_end() -> None:
    tr = EpisodeTracker(goal_xy=(50.0, 0.0), timeout_s=60.0)
    with pytest.raises(ValueError, match="goal_xy"):  # at the start, before any step could end the episode
        tr.start(_obs(0.0))


def test_first_collision_ends_with_its_kind_even_at_goal() -> None:
    hit = Event(EventKind.COLLISION, 0.1, 99.0, 0.0, other_id=7, other_type="pedestrian")
    tr = EpisodeTracker(goal_xy=(100.0, 0.0), timeout_s=60.0)
    tr.start(_obs(0.0))
    assert tr.update(_obs(99.0, events=(hit,)))
    res = tr.result()
    assert not res["success"] and res["reason"] == "collision_pedestrian"
    assert res["collisions"][0]["id"] == 7
    for other, reason in (("vehicle", "collision_vehicle"), ("static", "collision_static"), (None, "collision_static")):
        tr = EpisodeTracker(goal_xy=(100.0, 0.0), timeout_s=60.0)
        tr.start(_obs(0.0))
        tr.update(_obs(5.0, events=(Event(EventKind.COLLISION, 0.1, 5, 0, other_type=other),)))
        assert tr.result()["reason"] == reason


def test_timeout_and_counting_of_violations() -> None:
    tr = EpisodeTracker(goal_xy=(100.0, 0.0), timeout_s=0.3)
    tr.start(_obs(0.0))
    ev = (
        Event(EventKind.LANE_INVASION, 0.1, 1, 0, detail="opposite_lane"),
        Event(EventKind.LANE_INVASION, 0.1, 1, 0, detail="off_road"),
        Event(EventKind.RED_LIGHT, 0.1, 1, 0),
        Event(EventKind.LIGHT_PASSED, 0.1, 1, 0),
    )
    assert not tr.update(_obs(1.0, events=ev))
    assert not tr.update(_obs(2.0))
    assert tr.update(_obs(3.0))
    res = tr.result()
    assert res["reason"] == "timeout" and not res["success"]
    assert (res["lane_opposite"], res["lane_offroad"], res["red_lights"], res["lights_passed"]) == (1, 1, 1, 1)
    with pytest.raises(RuntimeError):
        tr.update(_obs(4.0))


def test_bad_lane_detail_is_an_error() -> None:
    tr = EpisodeTracker(goal_xy=(100.0, 0.0), timeout_s=10)
    tr.start(_obs(0.0))
    with pytest.raises(ValueError, match="opposite_lane"):
        tr.update(_obs(1.0, events=(Event(EventKind.LANE_INVASION, 0.1, 1, 0, detail="sidewalk"),)))


def test_violations_count_successful_episodes_only() -> None:
    recs = [_rec(0, True, km=2.0, opp=1, off=1, red=1, passed=4), _rec(0, False, km=5.0, opp=50, red=9, passed=9)]
    assert lane_violations_per_km(recs) == pytest.approx(1.0)
    assert light_violation_ratio(recs) == pytest.approx(0.25)
    assert math.isnan(lane_violations_per_km([_rec(0, False)]))
    assert math.isnan(light_violation_ratio([_rec(0, True, passed=0)]))


def test_best_of_for_static_mean_std_for_dynamic() -> None:
    recs = []
    for seed, n_ok in enumerate([2, 4, 3]):
        recs += [_rec(seed, i < n_ok) for i in range(4)]
    static = task_success(recs, dynamic=False)
    assert static.value == 100.0 and static.std is None and static.per_seed == (50.0, 100.0, 75.0)
    dyn = task_success(recs, dynamic=True)
    assert dyn.value == pytest.approx(75.0)
    assert dyn.std == pytest.approx(np.std([50.0, 100.0, 75.0]))  # population std, as the paper's figures
    assert dyn.format() == "75.00 ± 20.41"
    assert static.format() == "100"


def test_population_std_reproduces_the_papers_figures() -> None:
    assert mean_std([66.0, 66.0, 68.0]).format() == "66.67 ± 0.94"  # Table III, CILRS dense
    assert mean_std([31, 32, 32, 32, 31]).format() == "31.60 ± 0.49"  # Table II, yaw guidance sigma 10


def test_violation_stats_per_seed() -> None:
    recs = [_rec(0, True, km=1.0, opp=2, red=1, passed=2), _rec(1, True, km=1.0, opp=4, red=0, passed=2)]
    lanes, lights = task_violations(recs)
    assert lanes.value == pytest.approx(3.0) and lanes.std == pytest.approx(1.0)
    assert lights.value == pytest.approx(0.25) and lights.std == pytest.approx(0.25)
    assert math.isnan(mean_std([math.nan]).value)
    assert mean_std([1.0, math.nan, 3.0]).value == 2.0


def test_rates_and_counts() -> None:
    recs = [_rec(0, True), _rec(0, False, reason="collision_vehicle"), _rec(0, False)]
    assert success_rate(recs) == pytest.approx(100 / 3)
    counts = failure_counts(recs)
    assert counts["success"] == 1 and counts["collision_vehicle"] == 1 and counts["timeout"] == 1
    assert counts["rear_end"] == 0
    rear = _rec(0, False, reason="collision_vehicle")
    rear["collisions"] = [{"type": "vehicle", "rear_end": True}]
    assert failure_counts([*recs, rear])["rear_end"] == 1
    with pytest.raises(ValueError):
        success_rate([])
    with pytest.raises(ValueError):
        best_of([])
    with pytest.raises(ValueError, match="lacks field"):
        task_success([{"task": "x"}], dynamic=True)


def test_rear_end_is_a_vehicle_ahead_heading_our_way() -> None:
    from types import SimpleNamespace

    from yawil.bench.metrics import is_rear_end
    from yawil.sim.types import AgentState, Pose

    def obs(x: float, y: float, yaw: float) -> SimpleNamespace:
        car = AgentState(7, "vehicle", x, y, yaw, 0.0, 4.6, 1.9)
        return SimpleNamespace(pose=Pose(0.0, 0.0, 0.0), privileged=SimpleNamespace(agents=(car,)))

    assert is_rear_end(obs(4.0, 0.3, 0.1), 7)  # type: ignore[arg-type]
    assert not is_rear_end(obs(-4.0, 0.0, 0.0), 7)  # type: ignore[arg-type]  # it ran into us
    assert not is_rear_end(obs(4.0, 0.0, math.pi), 7)  # type: ignore[arg-type]  # head-on
    assert not is_rear_end(obs(4.0, 0.0, math.pi / 2), 7)  # type: ignore[arg-type]  # crossing
    assert not is_rear_end(obs(4.0, 0.0, 0.0), 8)  # type: ignore[arg-type]  # unknown id


def test_one_seed_shows_no_spread() -> None:
    from yawil.bench.metrics import mean_std

    assert mean_std([34.0]).format() == "34" and mean_std([100 / 3]).format() == "33.33"  # not "34.00 ± 0.00"


@given(st.integers(0, 500), st.integers(1, 500))
def test_wilson_interval_holds_the_rate_inside_0_100_and_narrows(k: int, n: int) -> None:
    from yawil.bench.metrics import wilson_interval

    k = min(k, n)
    lo, hi = wilson_interval(k, n)
    assert 0.0 <= lo <= 100 * k / n <= hi <= 100.0
    lo4, hi4 = wilson_interval(4 * k, 4 * n)
    assert hi4 - lo4 < hi - lo + 1e-9


def test_wilson_interval_known_values() -> None:
    from yawil.bench.metrics import wilson_interval

    lo, hi = wilson_interval(17, 50)  # the zoo YILRatt on the dense cell
    assert (round(lo, 1), round(hi, 1)) == (22.4, 47.8)
    assert wilson_interval(0, 10)[0] == 0.0 and wilson_interval(10, 10)[1] == 100.0


def test_difference_interval_known_values() -> None:
    """Newcombe (1998), Statistics in Medicine 17: 873-890, Table II example (a): 56/70 against 48/80, his
    method 10 gives 0.0524 to 0.3339."""
    from yawil.bench.metrics import difference_interval

    d, lo, hi = difference_interval((56, 70), (48, 80))
    assert round(d, 2) == 20.0 and (round(lo, 2), round(hi, 2)) == (5.24, 33.39)


@given(st.integers(0, 60), st.integers(1, 60), st.integers(0, 60), st.integers(1, 60))
def test_difference_interval_holds_the_difference_and_is_antisymmetric(ka: int, na: int, kb: int, nb: int) -> None:
    from yawil.bench.metrics import difference_interval

    ka, kb = min(ka, na), min(kb, nb)
    d, lo, hi = difference_interval((ka, na), (kb, nb))
    assert -100.0 <= lo <= d <= hi <= 100.0
    d2, lo2, hi2 = difference_interval((kb, nb), (ka, na))
    assert abs(d + d2) < 1e-9 and abs(lo + hi2) < 1e-9 and abs(hi + lo2) < 1e-9
