"""CarlaWorld end to end against `FakeCarlaServer` (tests/carla_fakes.py), a stand-in for the server."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

import carla
import numpy as np
import pytest

from carla_fakes import VERSION, FakeBlueprint, FakeCarlaServer
from yawil.expert import Expert
from yawil.sim import make_world
from yawil.sim.carla import convert
from yawil.sim.carla.errors import CarlaSetupError, SimulatorError
from yawil.sim.carla.world import CarlaWorld, carla_town
from yawil.sim.types import Control, Event, EventKind, Pose, RoadOption, Scenario


# ------------------------------------------------------------------------------------------------ tests
@pytest.fixture
def server() -> FakeCarlaServer:
    return FakeCarlaServer(town="Town02")


@pytest.fixture
def world(server: FakeCarlaServer) -> Iterator[CarlaWorld]:
    w = make_world("carla", host="fake", port=2000, timeout=2.0, client=server)
    assert isinstance(w, CarlaWorld)
    yield w
    w.close()


def left_turn(server: FakeCarlaServer) -> tuple[Pose, Pose]:
    """30 m before the central crossing (the approach with the light) to 25 m after its left exit."""
    topo = server.map.real.get_topology()
    a = server.approach
    exits = [bb for aa, bb in topo if aa.is_junction and aa.transform.location.distance(a.transform.location) < 0.5]
    start = convert.pose_from_transform(a.previous(30.0)[0].transform)
    for e in exits:
        goal = convert.pose_from_transform(e.next(25.0)[0].transform)
        if 0.5 < math.remainder(goal.yaw - start.yaw, 2 * math.pi) < 2.5:
            return start, goal
    raise AssertionError("no left exit")


def test_town_names_map_to_carla_maps() -> None:
    assert carla_town("town01") == "Town01" and carla_town("TOWN02") == "Town02"
    with pytest.raises(ValueError, match="CARLA's own maps"):
        carla_town("square")


def test_absent_server_is_a_clear_setup_error() -> None:
    t0 = time.monotonic()
    with pytest.raises(CarlaSetupError, match=r"no CARLA server answers at 127\.0\.0\.1:2\d{3}.*CarlaUE4\.sh"):
        CarlaWorld(host="127.0.0.1", port=2999, timeout=0.5)
    assert time.monotonic() - t0 < 30  # the client's own time-out, not a hang


def test_version_mismatch_names_both_versions() -> None:
    with pytest.raises(CarlaSetupError, match=rf"version 0\.9\.11 but the client package is {VERSION}"):
        CarlaWorld(client=FakeCarlaServer(version="0.9.11"))
    CarlaWorld(client=FakeCarlaServer(version=VERSION + "-dirty")).close()  # build suffixes are the same release


def test_bad_arguments_are_value_errors(server: FakeCarlaServer) -> None:
    with pytest.raises(ValueError, match="port"):
        CarlaWorld(port=0, client=server)
    with pytest.raises(ValueError, match="timeout"):
        CarlaWorld(timeout=-1, client=server)
    w = CarlaWorld(client=server)
    with pytest.raises(ValueError, match="CARLA's own maps"):
        w.reset(Scenario(town="square"), seed=0)
    with pytest.raises(RuntimeError, match="reset"):
        w.step(Control())


def test_reset_sets_up_the_protocol(server: FakeCarlaServer, world: CarlaWorld) -> None:
    start, goal = left_turn(server)
    obs = world.reset(Scenario(town="town01", start=start, goal=goal, weather="WetNoon", vehicles=3, pedestrians=2), seed=7)
    assert server.loads == ["Town01"]
    assert server.settings.synchronous_mode and server.settings.fixed_delta_seconds == pytest.approx(0.1)
    assert ("set_synchronous_mode", True) in server.tm_calls and ("set_random_device_seed", 7) in server.tm_calls
    assert server.weather == carla.WeatherParameters.WetNoon
    types = sorted(a.type_id for a in server.actors.values())
    assert types.count("sensor.camera.rgb") == 1 and "sensor.other.collision" in types and "sensor.other.lane_invasion" in types
    cars = [a for a in server.actors.values() if a.type_id.startswith("vehicle.") and a is not server.ego]
    assert len(cars) == 3 and all(("set_autopilot", True, 8000) in c.calls for c in cars)
    assert all("yamaha" not in c.type_id for c in cars)  # four wheels only
    ctrls = [a for a in server.actors.values() if a.type_id == "controller.ai.walker"]
    assert len(ctrls) == 2 and all(c.calls[0][0] == "start" and c.calls[1][0] == "go_to_location" for c in ctrls)
    assert server.ego.type_id == "vehicle.lincoln.mkz_2017"
    cam = next(a for a in server.actors.values() if a.type_id == "sensor.camera.rgb")
    assert cam.parent is server.ego and cam.transform.location.x == 2.0 and cam.transform.location.z == pytest.approx(1.4)
    # the observation, in yawil's frame
    assert obs.image is not None and obs.image.shape == (88, 200, 3) and obs.image.dtype == np.uint8
    assert math.hypot(obs.pose.x - start.x, obs.pose.y - start.y) < 0.5 and math.cos(obs.pose.yaw - start.yaw) > 0.99
    assert obs.town == "town01" and obs.weather == "WetNoon" and obs.frame == 0 and obs.events == ()
    assert obs.route.lights and obs.route.lights[0][1] == server.light.id
    assert RoadOption.LEFT in obs.route.options.tolist()
    assert obs.privileged.lights[0].state == "red" and len([a for a in obs.privileged.agents if a.kind == "vehicle"]) <= 3


def test_expert_drives_a_left_turn_stopping_at_the_red_light(server: FakeCarlaServer, world: CarlaWorld) -> None:
    """yawil's expert, reading CarlaWorld's privileged ground truth, waits at red and turns left to the goal."""
    start, goal = left_turn(server)
    obs = world.reset(Scenario(town="town01", start=start, goal=goal, camera=False), seed=1)
    expert = Expert()
    expert.reset()
    events: list[Event] = []
    stopped_at_red = False
    while not obs.done:
        obs = world.step(expert.act(obs))
        events += obs.events
        if obs.privileged.lights[0].state == "red" and obs.speed < 0.05 and obs.time > 3.0:
            stopped_at_red = True
    kinds = [e.kind for e in events]
    assert stopped_at_red and EventKind.GOAL_REACHED in kinds
    assert EventKind.LIGHT_PASSED in kinds and EventKind.RED_LIGHT not in kinds
    assert EventKind.COLLISION not in kinds and EventKind.LANE_INVASION not in kinds
    assert obs.command is RoadOption.LANEFOLLOW and obs.distance_driven == pytest.approx(obs.route.length, abs=4.0)


def test_collision_off_road_and_timeout_events(server: FakeCarlaServer, world: CarlaWorld) -> None:
    start, goal = left_turn(server)
    obs = world.reset(Scenario(town="town01", start=start, goal=goal, camera=False, timeout_s=6.0), seed=2)
    ahead = convert.pose_to_transform(Pose(start.x + 12 * math.cos(start.yaw), start.y + 12 * math.sin(start.yaw), start.yaw))
    parked = server.try_spawn_actor(FakeBlueprint("vehicle.audi.tt"), ahead)
    assert parked is not None
    events: list[Event] = []
    while not obs.done:
        obs = world.step(Control(steer=0.0, throttle=0.6))
        events += obs.events
    hits = [e for e in events if e.kind is EventKind.COLLISION]
    assert [(e.other_type, e.other_id) for e in hits] == [("vehicle", parked.id)]  # once per contact
    assert events[-1].kind is EventKind.TIMEOUT and obs.time == pytest.approx(6.0)
    obs = world.reset(Scenario(town="town01", start=start, goal=goal, camera=False), seed=2)
    for _ in range(40):
        obs = world.step(Control(steer=0.6, throttle=0.5))
        if any(e.kind is EventKind.LANE_INVASION for e in obs.events):
            break
    assert [e.detail for e in obs.events if e.kind is EventKind.LANE_INVASION] == ["off_road"]


def test_same_seed_same_episode(server: FakeCarlaServer) -> None:
    start, goal = left_turn(server)
    sc = Scenario(town="town01", start=start, goal=goal, vehicles=4, camera=False)
    runs = []
    for _ in range(2):
        w = CarlaWorld(client=server)
        obs = w.reset(sc, seed=11)
        cars = sorted((a.type_id, round(a.transform.location.x, 3), round(a.transform.location.y, 3))
                      for a in server.actors.values() if a.type_id.startswith("vehicle.") and a is not server.ego)
        poses = [w.step(Control(throttle=0.4, steer=0.05)).pose for _ in range(10)]
        runs.append((cars, poses, obs.route.xy.tobytes()))
        w.close()
    assert runs[0] == runs[1]
    routes = []
    for _ in range(2):
        w = CarlaWorld(client=server)
        routes.append(w.reset(Scenario(town="town01", camera=False, min_route_length=200.0), seed=5).route)
        w.close()
    free, again = routes
    assert free.length >= 200.0 and np.array_equal(free.xy, again.xy)


def test_crash_is_a_simulator_error_then_reconnect(server: FakeCarlaServer, world: CarlaWorld) -> None:
    start, goal = left_turn(server)
    sc = Scenario(town="town01", start=start, goal=goal, camera=False)
    world.reset(sc, seed=0)
    world.step(Control(throttle=0.5))
    server.crashed = True
    with pytest.raises(SimulatorError, match="failed during step: time-out"):
        world.step(Control(throttle=0.5))
    with pytest.raises(RuntimeError, match="call reset"):  # the episode is over
        world.step(Control())
    with pytest.raises(CarlaSetupError, match="no CARLA server answers"):
        world.reconnect()  # still down
    server.crashed = False
    world.reconnect()
    obs = world.reset(sc, seed=0)
    assert obs.frame == 0 and len([a for a in server.actors.values() if a.type_id.startswith("vehicle.")]) == 1


def test_close_restores_settings_and_destroys_actors(server: FakeCarlaServer) -> None:
    w = CarlaWorld(client=server)
    start, goal = left_turn(server)
    w.reset(Scenario(town="town01", start=start, goal=goal, vehicles=2, pedestrians=1), seed=3)
    w.close()
    assert not server.settings.synchronous_mode  # the settings found on connect
    assert [a.type_id for a in server.actors.values()] == ["traffic.traffic_light"]
    assert ("set_synchronous_mode", False) == server.tm_calls[-1]


def test_a_reloaded_map_gets_its_new_light_actors(server: FakeCarlaServer) -> None:
    """Loading a map makes new traffic-light actors: a topology cached before (a route-file check on connect, the
    other town's episodes) must not keep the old ids, or every light would read as 'green'."""
    w = CarlaWorld(client=server)
    w.topology_of("Town01")
    old_light = server.light.id
    w.topology_of("Town02")
    start, goal = left_turn(server)
    obs = w.reset(Scenario(town="town01", start=start, goal=goal, camera=False), seed=0)
    assert server.loads == ["Town01", "Town02", "Town01"] and server.light.id != old_light
    assert obs.route.lights[0][1] == server.light.id and obs.privileged.lights[0].state == "red"
    w.close()
