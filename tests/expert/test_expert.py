"""The expert on synthetic observations (no simulator) and, at the end, in the embedded world."""

from __future__ import annotations

import math

import numpy as np
import pytest

from yawil.expert import Expert, ExpertConfig, expert_info
from yawil.sim.town.dynamics import EgoState, VehicleParams, step_bicycle
from yawil.sim.types import (
    DT,
    AgentState,
    Control,
    Event,
    LightState,
    Observation,
    Pose,
    Privileged,
    RoadOption,
    Route,
)

# ---------------------------------------------------------------------------------------------- helpers


def polyline(*pieces: np.ndarray) -> np.ndarray:
    pts = np.concatenate(pieces)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6])
    return np.asarray(pts[keep])


def straight(x0: float, x1: float, y: float = 0.0) -> np.ndarray:
    n = int(round(abs(x1 - x0))) + 1
    return np.stack([np.linspace(x0, x1, n), np.full(n, y)], axis=1)


def make_route(xy: np.ndarray, turn: tuple[int, int] | None = None, option: RoadOption = RoadOption.LEFT,
               lights: tuple[tuple[int, int], ...] = ()) -> Route:
    d = np.diff(xy, axis=0)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    yaw = np.concatenate([yaw, yaw[-1:]])
    options = np.full(len(xy), int(RoadOption.LANEFOLLOW), dtype=np.int8)
    if turn is not None:
        options[turn[0] : turn[1]] = int(option)
    return Route(xy=xy, options=options, lane_yaw=yaw, lights=lights)


def turn_route(sign: float = 1.0) -> Route:
    """30 m east, a quarter circle of radius 10 m to the left (sign=1) or right (-1), then 40 m on."""
    a = np.linspace(0.0, math.pi / 2, 16)
    arc = np.stack([30.0 + 10.0 * np.sin(a), sign * (10.0 - 10.0 * np.cos(a))], axis=1)
    north = np.stack([np.full(40, 40.0), sign * np.linspace(11.0, 50.0, 40)], axis=1)
    xy = polyline(straight(0.0, 30.0), arc, north)
    return make_route(xy, turn=(25, 48), option=RoadOption.LEFT if sign > 0 else RoadOption.RIGHT)


def observe(route: Route, x: float, y: float, yaw: float, speed: float, lights: tuple[LightState, ...] = (),
            agents: tuple[AgentState, ...] = (), frame: int = 0) -> Observation:
    idx = int(np.argmin(np.linalg.norm(route.xy - np.array([x, y]), axis=1)))
    return Observation(
        image=None, speed=speed, pose=Pose(x, y, yaw), route=route, route_index=idx,
        command=RoadOption(int(route.options[idx])), events=(), time=frame * DT, frame=frame, done=False,
        distance_driven=0.0, town="synthetic", bounds=(-10.0, -60.0, 100.0, 60.0), weather="ClearNoon",
        privileged=Privileged(lights=lights, agents=agents, ego_lane_yaw=yaw),
    )


def pedestrian(x: float, y: float, yaw: float = 0.0, speed: float = 0.0, ident: int = 7) -> AgentState:
    return AgentState(id=ident, kind="pedestrian", x=x, y=y, yaw=yaw, speed=speed, length=0.5, width=0.5)


def vehicle(x: float, y: float, yaw: float = 0.0, speed: float = 0.0, ident: int = 9) -> AgentState:
    return AgentState(id=ident, kind="vehicle", x=x, y=y, yaw=yaw, speed=speed, length=4.5, width=1.9)


class Bicycle:
    """The embedded backend's ego dynamics (kinematic bicycle, steer rate limit), to close the loop cheaply."""

    def __init__(self, x: float, y: float, yaw: float, speed: float = 0.0) -> None:
        self.state = EgoState(x, y, yaw, speed)
        self.params = VehicleParams()

    x = property(lambda self: self.state.x)
    y = property(lambda self: self.state.y)
    yaw = property(lambda self: self.state.yaw)
    speed = property(lambda self: self.state.speed)

    def step(self, c: Control) -> None:
        self.state = step_bicycle(self.state, c.validate(), self.params)


# ------------------------------------------------------------------------------------------ open loop


def test_straight_route_goes_straight_and_accelerates() -> None:
    route = make_route(straight(0.0, 100.0))
    c = Expert().act(observe(route, 10.0, 0.0, 0.0, 2.0))
    assert abs(c.steer) < 1e-6
    assert c.throttle > 0.1 and c.brake == 0.0


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_steers_into_the_turn(sign: float) -> None:
    route = turn_route(sign)
    c = Expert().act(observe(route, 30.0, 0.0, 0.0, 4.0))
    # CARLA convention: steer > 0 turns right; a left turn (yaw increasing) needs a negative steer
    assert c.steer * sign < -0.1


def test_steers_back_towards_the_route() -> None:
    route = make_route(straight(0.0, 100.0))
    c = Expert().act(observe(route, 10.0, -1.0, 0.0, 4.0))  # 1 m right of the route
    assert c.steer < -0.05


def test_slows_for_a_sharp_turn_ahead() -> None:
    e = Expert()
    e.act(observe(turn_route(), 30.0, 0.0, 0.0, 5.5))
    assert e.state.reason == "curve"
    assert e.state.target_speed < 5.0


def _light_route() -> Route:
    return make_route(straight(0.0, 100.0), turn=(30, 45), option=RoadOption.STRAIGHT, lights=((30, 3),))


def test_brakes_for_a_red_light_not_for_a_green_one() -> None:
    route = _light_route()
    red = (LightState(3, "red", 30.0, 0.0, 0.0),)
    e = Expert()
    c = e.act(observe(route, 22.0, 0.0, 0.0, 5.5, lights=red))
    assert c.brake > 0.0 and c.throttle == 0.0
    assert e.state.reason == "red_light"
    green = (LightState(3, "green", 30.0, 0.0, 0.0),)
    e2 = Expert()
    c2 = e2.act(observe(route, 22.0, 0.0, 0.0, 4.0, lights=green))
    assert c2.throttle > 0.0 and c2.brake == 0.0
    assert e2.state.reason == "cruise"


def test_yellow_light_stops_only_when_it_comfortably_can() -> None:
    route = _light_route()
    yellow = (LightState(3, "yellow", 30.0, 0.0, 0.0),)
    far = Expert()
    far.act(observe(route, 5.0, 0.0, 0.0, 5.5, lights=yellow))
    assert far.state.light_decisions == {3: "stop"}
    near = Expert()  # front bumper 0.8 m before the line at 5.5 m/s: cannot stop comfortably, goes on
    c = near.act(observe(route, 26.9, 0.0, 0.0, 5.5, lights=yellow))
    assert near.state.light_decisions == {3: "go"}
    assert near.state.reason != "yellow_light" and c.brake == 0.0


def test_red_light_behind_the_ego_is_ignored() -> None:
    route = _light_route()
    red = (LightState(3, "red", 30.0, 0.0, 0.0),)
    e = Expert()
    c = e.act(observe(route, 40.0, 0.0, 0.0, 4.0, lights=red))
    assert c.throttle > 0.0 and e.state.reason == "cruise"


def test_brakes_for_a_pedestrian_in_the_corridor_not_on_the_sidewalk() -> None:
    route = make_route(straight(0.0, 100.0))
    e = Expert()
    c = e.act(observe(route, 10.0, 0.0, 0.0, 5.0, agents=(pedestrian(18.0, 0.5),)))
    assert c.brake > 0.0 and e.state.reason == "pedestrian"
    far = Expert()
    c2 = far.act(observe(route, 10.0, 0.0, 0.0, 4.0, agents=(pedestrian(18.0, -6.0), pedestrian(30.0, 3.2, math.pi / 2, 1.2))))
    assert c2.throttle > 0.0 and c2.brake == 0.0 and far.state.reason == "cruise"


def test_pedestrian_about_to_enter_the_corridor_counts() -> None:
    route = make_route(straight(0.0, 100.0))
    walking_in = pedestrian(20.0, -4.0, math.pi / 2, 1.4)
    e = Expert()
    c = e.act(observe(route, 10.0, 0.0, 0.0, 5.0, agents=(walking_in,)))
    assert e.state.reason == "pedestrian" and c.brake > 0.0
    walking_away = pedestrian(20.0, -4.0, -math.pi / 2, 1.4)
    e2 = Expert()
    e2.act(observe(route, 10.0, 0.0, 0.0, 5.0, agents=(walking_away,)))
    assert e2.state.reason == "cruise"


def test_follows_a_lead_vehicle_and_ignores_oncoming_traffic() -> None:
    route = make_route(straight(0.0, 100.0))
    oncoming = vehicle(30.0, 3.5, math.pi, 5.0, ident=1)
    behind = vehicle(2.0, 0.0, 0.0, 6.0, ident=2)
    e = Expert()
    c = e.act(observe(route, 10.0, 0.0, 0.0, 4.0, agents=(oncoming, behind)))
    assert e.state.reason == "cruise" and c.throttle > 0.0
    stopped = vehicle(20.0, 0.2, 0.0, 0.0, ident=3)
    e2 = Expert()
    c2 = e2.act(observe(route, 10.0, 0.0, 0.0, 5.0, agents=(stopped,)))
    assert e2.state.reason == "vehicle" and c2.brake > 0.0
    assert expert_info(e2)["hazard"]["agent_id"] == 3


def test_yields_to_crossing_traffic_in_a_junction() -> None:
    route = make_route(straight(0.0, 100.0), turn=(30, 42), option=RoadOption.STRAIGHT, lights=((30, 3),))
    green = (LightState(3, "green", 30.0, 0.0, 0.0),)
    crossing = vehicle(36.0, -14.0, math.pi / 2, 6.0)  # from the right, reaches the path in ~2 s
    e = Expert()
    e.act(observe(route, 25.0, 0.0, 0.0, 5.0, lights=green, agents=(crossing,)))
    assert e.state.reason == "junction"
    gone = vehicle(36.0, 14.0, math.pi / 2, 6.0)  # already past the path, driving away
    e2 = Expert()
    e2.act(observe(route, 25.0, 0.0, 0.0, 5.0, lights=green, agents=(gone,)))
    assert e2.state.reason == "cruise"


def test_deterministic_and_reset() -> None:
    route = turn_route()
    obs = [observe(route, 20.0 + i, 0.0, 0.0, 3.0 + 0.1 * i, agents=(pedestrian(40.0, 8.0, -math.pi / 2, 1.0),))
           for i in range(10)]
    e = Expert()
    a = [e.act(o) for o in obs]
    e.reset()
    b = [e.act(o) for o in obs]
    assert a == b


def test_bad_config_is_an_error() -> None:
    with pytest.raises(ValueError, match="cruise_speed"):
        ExpertConfig(cruise_speed=0.0)
    with pytest.raises(ValueError, match="lookahead_max"):
        ExpertConfig(lookahead_min=5.0, lookahead_max=4.0)
    with pytest.raises(ValueError, match="kp"):
        ExpertConfig(kp=float("nan"))


def test_config_from_command_line_items() -> None:
    cfg = ExpertConfig.from_items(["comfort_decel=1.5", "vehicle_gap=3"])
    assert (cfg.comfort_decel, cfg.vehicle_gap, cfg.kp) == (1.5, 3.0, ExpertConfig().kp)
    assert cfg.changes() == {"comfort_decel": 1.5, "vehicle_gap": 3.0}
    assert ExpertConfig.from_items([]) == ExpertConfig() and ExpertConfig().changes() == {}
    with pytest.raises(ValueError, match="unknown expert setting 'brake'"):
        ExpertConfig.from_items(["brake=1"])
    with pytest.raises(ValueError, match="expected KEY=VALUE"):
        ExpertConfig.from_items(["comfort_decel"])
    with pytest.raises(ValueError, match="expected a number"):
        ExpertConfig.from_items(["comfort_decel=soft"])
    with pytest.raises(ValueError, match="comfort_decel"):
        ExpertConfig.from_items(["comfort_decel=0"])


# ---------------------------------------------------------------------------------------- closed loop


def _drive(route: Route, steps: int, lights: tuple[LightState, ...] = ()) -> tuple[Bicycle, float]:
    car = Bicycle(0.0, 0.0, 0.0)
    e = Expert()
    worst = 0.0
    for i in range(steps):
        o = observe(route, car.x, car.y, car.yaw, car.speed, lights=lights, frame=i)
        car.step(e.act(o))
        worst = max(worst, abs(e.state.lateral_error))
    return car, worst


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_closed_loop_turn_reaches_the_goal(sign: float) -> None:
    route = turn_route(sign)
    car, worst = _drive(route, 400)
    assert math.hypot(car.x - route.xy[-1, 0], car.y - route.xy[-1, 1]) < 2.0
    assert car.speed < 0.1  # stopped at the goal
    assert worst < 0.6  # metres off the route at most, in the turn


def test_closed_loop_stops_before_the_red_stop_line() -> None:
    route = _light_route()
    red = (LightState(3, "red", 30.0, 0.0, 0.0),)
    car, _ = _drive(route, 200, lights=red)
    front = car.x + 0.5 * ExpertConfig().length
    assert car.speed < 0.05
    assert 26.0 < front <= 30.0  # waiting behind the line, not far from it


def test_does_not_stop_inside_a_junction_or_on_its_crosswalks() -> None:
    # junction from the stop line at 30 m to the exit at 42 m; a vehicle stands just past the exit
    route = make_route(straight(0.0, 100.0), turn=(30, 42), option=RoadOption.STRAIGHT, lights=((30, 3),))
    green = (LightState(3, "green", 30.0, 0.0, 0.0),)
    queue_head = vehicle(47.0, 0.0, 0.0, 0.0)
    e = Expert()
    e.act(observe(route, 22.0, 0.0, 0.0, 5.0, lights=green, agents=(queue_head,)))
    assert e.state.reason == "vehicle" and e.state.hazard is not None
    front_at_stop = 22.0 + e.state.hazard.distance + 0.5 * ExpertConfig().length
    assert front_at_stop <= 30.0  # waits before the stop line, not in the box behind the vehicle
    far_away = vehicle(70.0, 0.0, 0.0, 0.0)  # enough room after the junction: no change
    e2 = Expert()
    e2.act(observe(route, 22.0, 0.0, 0.0, 5.0, lights=green, agents=(far_away,)))
    assert e2.state.reason == "cruise"


# --------------------------------------------------------------------------------------- embedded world


def test_drives_a_short_route_in_the_embedded_world() -> None:
    from yawil.sim import EventKind, Scenario, make_world

    world = make_world("embedded")
    try:
        obs = world.reset(Scenario(town="town02", vehicles=15, pedestrians=15, camera=False, min_route_length=100.0), 2)
        expert = Expert()
        events: list[Event] = []
        while not obs.done:
            obs = world.step(expert.act(obs))
            events.extend(obs.events)
    finally:
        world.close()
    kinds = [e.kind for e in events]
    assert EventKind.GOAL_REACHED in kinds
    assert EventKind.COLLISION not in kinds and EventKind.RED_LIGHT not in kinds
    assert EventKind.LANE_INVASION not in kinds
    assert EventKind.LIGHT_PASSED in kinds  # the route crosses a signalised junction


def test_waits_for_a_pedestrian_at_the_kerb_of_a_crosswalk_ahead() -> None:
    # junction from the stop line at 30 m to its exit at 42 m; the exit crosswalk spans 42-46 m
    route = make_route(straight(0.0, 100.0), turn=(30, 42), option=RoadOption.STRAIGHT, lights=((30, 3),))
    green = (LightState(3, "green", 30.0, 0.0, 0.0),)
    kerb = pedestrian(44.0, -3.0, 0.0, 0.0)  # standing at the kerb, right next to the crosswalk
    e = Expert()
    e.act(observe(route, 22.0, 0.0, 0.0, 5.0, lights=green, agents=(kerb,)))
    assert e.state.reason == "pedestrian" and e.state.hazard is not None
    assert 22.0 + e.state.hazard.distance + 0.5 * ExpertConfig().length <= 30.0  # waits at the stop line
    leaving = pedestrian(44.0, -3.0, -math.pi / 2, 1.4)  # walking away from the road
    mid_block = pedestrian(70.0, -3.0, 0.0, 0.0)  # on the sidewalk far from any crosswalk
    e2 = Expert()
    e2.act(observe(route, 22.0, 0.0, 0.0, 5.0, lights=green, agents=(leaving, mid_block)))
    assert e2.state.reason == "cruise"


def test_predicts_a_turning_vehicle_from_its_yaw_rate() -> None:
    route = make_route(straight(0.0, 100.0))

    def second_call(yaw_rate: float) -> str:
        e = Expert()
        e.act(observe(route, 25.0, 0.0, 0.0, 5.0, agents=(vehicle(30.0, -6.0, 0.0, 5.0),), frame=0))
        turning = vehicle(30.5, -6.0, yaw_rate * DT, 5.0)  # 0.1 s later, turning left towards the route
        e.act(observe(route, 25.5, 0.0, 0.0, 5.0, agents=(turning,), frame=1))
        return e.state.reason

    assert second_call(0.5) == "vehicle"  # on a 10 m radius it cuts across the ego's path in ~2 s
    assert second_call(0.0) == "cruise"  # driving straight on beside the route: no conflict


def test_a_pedestrian_stepping_out_too_close_to_stop_for_is_passed_not_braked_into() -> None:
    route = make_route(straight(0.0, 100.0))
    late = pedestrian(13.5, 3.0, -math.pi / 2, 1.4)  # 0.9 m ahead of the bumper, 1.6 m from the ego's side
    e = Expert()
    c = e.act(observe(route, 10.0, 0.0, 0.0, 5.5, agents=(late,)))
    assert c.brake == 0.0  # the ego is past in 1.1 s, the pedestrian needs 1.2 s: braking would stop in its way
    closer = pedestrian(13.5, 2.4, -math.pi / 2, 1.4)  # would touch the ego before it is past: brake
    e2 = Expert()
    c2 = e2.act(observe(route, 10.0, 0.0, 0.0, 5.5, agents=(closer,)))
    assert c2.brake > 0.0


def test_standing_for_crossing_traffic_it_starts_only_after_a_second_clear() -> None:
    """Town02 seed 44: a crossing prediction switched off for 0.7 s, the ego started, and such gaps had it
    creep onto the crosswalk past its stop line. Standing for an agent outside its lane, it now waits until
    the agent has been gone for `restart_hold` seconds."""
    route = make_route(straight(0.0, 100.0), turn=(30, 42), option=RoadOption.STRAIGHT, lights=((30, 3),))
    green = (LightState(3, "green", 30.0, 0.0, 0.0),)
    x = 30.0 - 1.0 - 0.5 * ExpertConfig().length  # waiting 1 m before the stop line
    crossing = (vehicle(36.0, -5.0, math.pi / 2, 3.0),)  # in the box, about to cross the ego's path
    e = Expert()
    controls = []
    for frame in range(25):
        agents = crossing if frame < 5 or frame == 17 else ()  # gone at frame 5 ... back for one frame at 17
        controls.append(e.act(observe(route, x, 0.0, 0.0, 0.0, lights=green, agents=agents, frame=frame)))
        if frame < 5:
            assert e.state.reason == "junction"
    assert all(c.throttle == 0.0 and c.brake > 0.0 for c in controls[:14])  # last seen at 0.4 s: held to 1.4 s
    assert controls[14].throttle > 0.0 and controls[16].throttle > 0.0  # then it starts
    assert controls[17].brake > 0.0  # (the agent back: stop again)
    assert all(c.throttle == 0.0 for c in controls[18:])  # and hold another second, not 0.1 s
    moving = Expert()  # already rolling, nothing is held: what is gone is gone
    moving.act(observe(route, x - 10.0, 0.0, 0.0, 4.0, lights=green, agents=crossing, frame=0))
    assert moving.act(observe(route, x - 9.6, 0.0, 0.0, 4.0, lights=green, frame=1)).throttle > 0.0


def test_a_vehicle_its_red_light_stops_is_not_crossing_traffic() -> None:
    """Town02, dense: a car approaching its red light looked about to cross the ego's path, and the ego let
    its short green go by. Traffic obeys the lights; a yellow it cannot stop for comfortably it still runs."""
    route = make_route(straight(0.0, 100.0), turn=(30, 42), option=RoadOption.STRAIGHT, lights=((30, 3),))

    def reason(state: str, y_car: float = -24.0) -> str:
        lights = (LightState(3, "green", 30.0, 0.0, 0.0), LightState(4, state, 37.75, -10.0, math.pi / 2))
        car = (vehicle(37.75, y_car, math.pi / 2, 6.0),)  # from the south at 6 m/s: across the path in ~3.5 s
        e = Expert()
        e.act(observe(route, 25.0, 0.0, 0.0, 5.0, lights=lights, agents=car))
        return e.state.reason

    assert reason("green") in ("junction", "vehicle")
    assert reason("red") == "cruise"  # it stops at its line, 10 m before the ego's path
    assert reason("yellow") == "cruise"  # 11.75 m to its line: 3 m/s^2 suffice, it stops
    assert reason("yellow", -14.0) in ("junction", "vehicle")  # 1.75 m to its line at 6 m/s: it runs the yellow


def test_a_vehicle_standing_just_past_the_goal_is_not_run_into() -> None:
    """Town02 dense 4/2 and 24/2: the corridors ended at the goal, so the tail of a queue standing just past
    it was invisible, and the ego, planning to stop with its front 3 m past the goal, ran into it."""
    route = make_route(straight(0.0, 50.0))
    queue_tail = vehicle(50.0 + 0.5 * 4.5 + 1.0, 0.0, 0.0, 0.0)  # its rear 1 m past the goal
    car = Bicycle(20.0, 0.0, 0.0, speed=5.0)
    e = Expert()
    for i in range(200):
        car.step(e.act(observe(route, car.x, car.y, car.yaw, car.speed, agents=(queue_tail,), frame=i)))
        assert car.x + 0.5 * ExpertConfig().length < 51.0  # never touches its rear
    assert car.speed < 0.05 and car.x > 44.0  # stopped behind it, near the goal


def test_points_past_the_goal_lie_on_the_route_s_extension() -> None:
    """The tail added past the goal must not shift what lies beyond the route's end (pure pursuit aims there
    near the goal): 3 m past the end is 3 m past the goal point, not 3 m past the tail."""
    from yawil.expert.route import RouteCache

    rc = RouteCache(make_route(straight(0.0, 50.0)))
    assert rc.length == pytest.approx(50.0)
    for ahead in (0.0, 3.0, 11.0, 20.0):
        assert rc.point_at(50.0 + ahead) == pytest.approx(np.array([50.0 + ahead, 0.0]))


def test_room_before_lights_equals_one_light_at_a_time() -> None:
    """The (lights x vehicles) form gives, to the last bit, what the per-light loop it replaced gave."""
    import math

    from yawil.sim.types import LightState, wrap_angle

    expert = Expert()

    def reference(lights, pos, yaw, spd, length, is_ped):  # type: ignore[no-untyped-def]
        room = np.full(len(pos), np.inf)
        for ls in lights:
            if ls.state == "green":
                continue
            c, s = math.cos(ls.yaw), math.sin(ls.yaw)
            rx, ry = ls.x - pos[:, 0], ls.y - pos[:, 1]
            ahead = rx * c + ry * s - 0.5 * length
            lane = (np.abs(-rx * s + ry * c) < 1.75) & (np.abs(wrap_angle(yaw - ls.yaw)) < math.radians(30.0))
            stops = ~is_ped & lane & (ahead > -0.5) & (ahead < 60.0)
            if ls.state == "yellow":
                stops &= ahead >= spd * spd / (2.0 * expert.config.traffic_yellow_decel)
            room = np.where(stops, np.minimum(room, np.maximum(ahead, 0.0)), room)
        return room

    rng = np.random.default_rng(0)
    finite = 0
    for _ in range(300):
        n_lights, n = int(rng.integers(0, 30)), int(rng.integers(0, 40))
        lights = tuple(LightState(i, str(rng.choice(["red", "yellow", "green"])), *rng.uniform(0, 100, 2),
                                  float(rng.uniform(-4, 4))) for i in range(n_lights))
        pos, yaw = rng.uniform(0, 100, (n, 2)), rng.uniform(-4, 4, n)
        for j in range(min(n, n_lights)):  # vehicles in the lane before a light, some past it
            ls, d = lights[j], rng.uniform(-1, 70)
            pos[j] = (ls.x - d * math.cos(ls.yaw) + rng.normal(0, 1), ls.y - d * math.sin(ls.yaw) + rng.normal(0, 1))
            yaw[j] = ls.yaw + rng.normal(0, 0.3)
        args = (lights, pos, yaw, rng.uniform(0, 10, n), rng.uniform(3, 6, n), rng.random(n) < 0.3)
        got, want = expert._room_before_lights(*args), reference(*args)
        assert got.shape == want.shape and np.array_equal(got, want)
        finite += int(np.isfinite(got).sum())
    assert finite > 100  # the draws did put vehicles before red and yellow lights
