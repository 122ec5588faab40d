"""EmbeddedWorld without traffic: dynamics, driving a route, determinism, bad input, commands."""

from __future__ import annotations

import math

import numpy as np
import pytest

from yawil.sim import Control, Event, EventKind, Pose, RoadOption, Scenario, World, make_world
from yawil.sim.cli import follow_route
from yawil.sim.criteria import nocrash_timeout
from yawil.sim.town.dynamics import EgoState, VehicleParams, longitudinal_accel, step_bicycle
from yawil.sim.town.world import EmbeddedWorld

LEFT_TURN = Scenario(town="square", start=Pose(1.75, -50.0, math.pi / 2), goal=Pose(-40.0, 1.75, math.pi), camera=False)


def test_make_world_and_protocol() -> None:
    w = make_world("embedded")
    assert isinstance(w, World) and isinstance(w, EmbeddedWorld)
    with pytest.raises(ValueError, match="embedded"):
        make_world("unreal")


def test_bicycle_steer_sign_speed_limit_and_brake() -> None:
    p = VehicleParams()
    s = EgoState(0.0, 0.0, 0.0, speed=5.0)
    for _ in range(20):
        s = step_bicycle(s, Control(steer=0.5, throttle=0.3), p)
    assert s.yaw < -0.3 and s.y < 0  # steer > 0 turns right (clockwise), as CARLA
    assert abs(s.wheel) <= p.max_steer + 1e-12
    fast = EgoState(0.0, 0.0, 0.0)
    for _ in range(2000):
        fast = step_bicycle(fast, Control(throttle=1.0), p)
    assert 0.8 * p.max_speed < fast.speed < p.max_speed
    for _ in range(60):
        fast = step_bicycle(fast, Control(brake=1.0), p)
    assert fast.speed == 0.0
    assert longitudinal_accel(p, 0.0, 1.0, 0.0) == pytest.approx(p.max_accel)
    # steering is rate-limited: one step cannot reach full lock
    one = step_bicycle(EgoState(0, 0, 0, 5.0), Control(steer=1.0), p)
    assert abs(one.wheel) < p.max_steer


def test_follow_a_left_turn_to_the_goal() -> None:
    w = EmbeddedWorld()
    obs = w.reset(LEFT_TURN, seed=0)
    assert obs.image is None and obs.frame == 0 and obs.route_index == 0
    assert obs.command is RoadOption.LANEFOLLOW
    assert obs.bounds == w.town.geometry.bounds  # type: ignore[union-attr]
    commands: list[RoadOption] = []
    events: list[Event] = []
    while not obs.done:
        obs = w.step(follow_route(obs))
        commands.append(obs.command)
        events += obs.events
        assert obs.time < 60
    kinds = [e.kind for e in events]
    assert kinds.count(EventKind.GOAL_REACHED) == 1
    assert EventKind.COLLISION not in kinds and EventKind.LANE_INVASION not in kinds
    assert RoadOption.LEFT in commands and commands[-1] is RoadOption.LANEFOLLOW
    assert obs.distance_driven == pytest.approx(obs.route.length, rel=0.05)
    assert abs(obs.privileged.ego_lane_yaw - math.pi) < 0.1
    assert len(obs.privileged.lights) == 16 and {ls.state for ls in obs.privileged.lights} <= {"red", "yellow", "green"}


def test_same_seed_same_episode_bit_for_bit() -> None:
    sc = Scenario(town="town02", vehicles=20, pedestrians=15, camera=False, min_route_length=200.0)

    def run(seed: int) -> list[tuple]:
        w = EmbeddedWorld()
        obs = w.reset(sc, seed)
        out = []
        for k in range(120):
            obs = w.step(follow_route(obs) if k % 7 else Control(0.1, 0.4, 0.0))
            out.append((obs.pose, obs.speed, obs.command, obs.privileged, obs.events, obs.route_index))
        out.append((w.vehicles.x.tobytes(), w.pedestrians.xy.tobytes()))  # type: ignore[arg-type]
        return out

    a, b = run(5), run(5)
    assert a == b
    assert run(6)[-1] != a[-1]


def test_timeout_and_nocrash_formula() -> None:
    assert nocrash_timeout(1000.0) == pytest.approx(740.0)
    w = EmbeddedWorld()
    obs = w.reset(Scenario(town="square", timeout_s=1.0, camera=False), seed=3)
    assert w.timeout_s == 1.0
    n = 0
    while not obs.done:
        obs = w.step(Control())
        n += 1
    assert n == 10 and [e.kind for e in obs.events] == [EventKind.TIMEOUT]
    obs = w.reset(Scenario(town="square", camera=False), seed=3)
    assert w.timeout_s == pytest.approx(nocrash_timeout(obs.route.length))


@pytest.mark.parametrize("bad", [Control(steer=float("nan")), Control(steer=1.5), Control(throttle=-0.1),
                                 Control(brake=2.0), Control(throttle=float("inf"))])
def test_bad_controls_raise(bad: Control) -> None:
    w = EmbeddedWorld()
    w.reset(Scenario(town="square", camera=False), seed=0)
    with pytest.raises(ValueError, match="Control"):
        w.step(bad)


def test_bad_scenarios_raise() -> None:
    w = EmbeddedWorld()
    with pytest.raises(RuntimeError, match="reset"):
        w.step(Control())
    with pytest.raises(ValueError, match="ClearNoon"):
        w.reset(Scenario(town="square", weather="Snow", camera=False), seed=0)
    with pytest.raises(ValueError, match="town01"):
        w.reset(Scenario(town="gotham", camera=False), seed=0)
    with pytest.raises(ValueError, match="vehicles"):
        w.reset(Scenario(town="square", vehicles=-1, camera=False), seed=0)
    with pytest.raises(ValueError, match="timeout_s"):
        w.reset(Scenario(town="square", timeout_s=0.0, camera=False), seed=0)
    with pytest.raises(ValueError, match="seed"):
        w.reset(Scenario(town="square", camera=False), seed=-1)
    with pytest.raises(ValueError, match="Use fewer"):
        w.reset(Scenario(town="square", vehicles=400, camera=False), seed=0)
    with pytest.raises(ValueError, match="at least 5000"):
        w.reset(Scenario(town="square", min_route_length=5000.0, camera=False), seed=0)


def test_random_routes_respect_min_length_and_given_start() -> None:
    w = EmbeddedWorld()
    obs = w.reset(Scenario(town="town02", min_route_length=300.0, camera=False), seed=11)
    assert obs.route.length >= 300.0
    start = Pose(float(obs.route.xy[0, 0]), float(obs.route.xy[0, 1]), float(obs.route.lane_yaw[0]))
    obs2 = w.reset(Scenario(town="town02", start=start, min_route_length=100.0, camera=False), seed=12)
    assert np.allclose(obs2.route.xy[0], obs.route.xy[0], atol=0.5)

