"""CarlaWorld end to end against `FakeCarlaServer`, a stand-in for the server (no CARLA server runs here).

The stand-in answers the client calls CarlaWorld makes. Its map is REAL: a carla.Map the client library
builds offline from tests/fixtures/carla/grid.xodr (a 3x3 street grid), so waypoints, topology, junction
flags and off-road queries are CARLA's own. What it fakes: actors, ticking (the ego moves by yawil's
kinematic bicycle), the camera (a BGRA gradient), collisions (ego within 3 m of another vehicle), one traffic
light (red for the first 12 s), the Traffic Manager and walker controllers (recorded, not simulated), and
crashes on demand. Lives in tests/ only; the package never imports it.
"""

from __future__ import annotations

import fnmatch
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import carla
import numpy as np
import pytest

from yawil.expert import Expert
from yawil.sim import make_world
from yawil.sim.carla import convert
from yawil.sim.carla.errors import CarlaSetupError, SimulatorError
from yawil.sim.carla.world import CarlaWorld, carla_town
from yawil.sim.town.dynamics import EgoState, VehicleParams, step_bicycle
from yawil.sim.types import Control, Event, EventKind, Pose, RoadOption, Scenario

XODR = Path(__file__).parent / "fixtures" / "carla" / "grid.xodr"
VERSION = carla.Client("localhost", 2000).get_client_version()


class FakeBlueprint:
    def __init__(self, bp_id: str, **attrs: str) -> None:
        self.id = bp_id
        self.attrs = dict(attrs)

    def has_attribute(self, key: str) -> bool:
        return key in self.attrs

    def set_attribute(self, key: str, value: str) -> None:
        self.attrs[key] = value

    def get_attribute(self, key: str) -> Any:
        value = self.attrs[key]

        class Attr:
            def as_int(self) -> int:
                return int(value)

        return Attr()


class FakeLibrary:
    def __init__(self) -> None:
        ids = ["vehicle.lincoln.mkz_2017", "vehicle.tesla.model3", "vehicle.audi.tt", "vehicle.yamaha.yzf",
               "walker.pedestrian.0001", "walker.pedestrian.0002", "controller.ai.walker", "sensor.camera.rgb",
               "sensor.other.collision", "sensor.other.lane_invasion"]
        self.bps = [FakeBlueprint(i, number_of_wheels="2" if "yamaha" in i else "4", role_name="")
                    if i.startswith("vehicle.") else FakeBlueprint(i) for i in ids]

    def find(self, bp_id: str) -> FakeBlueprint:
        for b in self.bps:
            if b.id == bp_id:
                return FakeBlueprint(b.id, **b.attrs)
        raise IndexError(f"blueprint {bp_id} not found")

    def filter(self, pattern: str) -> list[FakeBlueprint]:
        return [FakeBlueprint(b.id, **b.attrs) for b in self.bps if fnmatch.fnmatch(b.id, pattern)]


class FakeActor:
    def __init__(self, server: FakeCarlaServer, type_id: str, transform: carla.Transform, parent: FakeActor | None) -> None:
        self.server, self.type_id, self.parent = server, type_id, parent
        self.id = server.next_id()
        self.transform = transform
        self.velocity = carla.Vector3D(0.0, 0.0, 0.0)
        self.bounding_box = carla.BoundingBox(carla.Location(), carla.Vector3D(2.4, 1.0, 0.8))
        self.callback: Callable[[Any], None] | None = None
        self.calls: list[tuple[Any, ...]] = []
        self.state = carla.TrafficLightState.Red
        self.stop_waypoints: list[carla.Waypoint] = []

    def get_transform(self) -> carla.Transform:
        return self.transform

    def get_velocity(self) -> carla.Vector3D:
        return self.velocity

    def destroy(self) -> bool:
        self.server.check()
        self.server.actors.pop(self.id, None)
        return True

    def listen(self, callback: Callable[[Any], None]) -> None:
        self.callback = callback

    def stop(self) -> None:
        self.callback = None

    def apply_control(self, control: carla.VehicleControl) -> None:
        self.server.ego_control = Control(steer=control.steer, throttle=control.throttle, brake=control.brake)

    def get_state(self) -> carla.TrafficLightState:
        return self.state

    def get_stop_waypoints(self) -> list[carla.Waypoint]:
        return self.stop_waypoints

    def __getattr__(self, name: str) -> Callable[..., None]:  # set_autopilot, start, go_to_location, set_max_speed
        def record(*args: Any) -> None:
            self.calls.append((name, *args))

        return record


class FakeMap:
    """A real carla.Map named like a town, with spawn points (an OpenDRIVE file alone has none)."""

    def __init__(self, name: str) -> None:
        self.real = carla.Map(name, XODR.read_text(encoding="utf-8"))
        self.name = f"Carla/Maps/{name}"
        self.spawns = [w.transform for a, _ in self.real.get_topology() if not a.is_junction for w in a.next(40.0)[:1]]

    def get_spawn_points(self) -> list[carla.Transform]:
        return [carla.Transform(carla.Location(t.location.x, t.location.y, 0.5), t.rotation) for t in self.spawns]

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real, name)


class FakeActorList(list):  # type: ignore[type-arg]
    def filter(self, pattern: str) -> FakeActorList:
        return FakeActorList(a for a in self if fnmatch.fnmatch(a.type_id, pattern))


class FakeCarlaServer:
    """Stand-in for a CARLA server and its client object (see the module docstring for what it fakes)."""

    def __init__(self, version: str = VERSION, town: str = "Town01") -> None:
        self.version = version
        self.crashed = False
        self._id = 100
        self.actors: dict[int, FakeActor] = {}
        self.settings = carla.WorldSettings()
        self.settings_history: list[carla.WorldSettings] = []
        self.weather: carla.WeatherParameters | None = None
        self.tm_calls: list[tuple[Any, ...]] = []
        self.loads: list[str] = []
        self.frame = 0
        self.ego_control = Control()
        self.ego_state: EgoState | None = None
        self.params = VehicleParams()
        self.nav_points = [carla.Location(x=float(x), y=float(y), z=0.0) for x, y in ((3, -3), (147, -5), (297, -150), (150, -297))]
        self.nav_index = 0
        self.light_red_until = 120
        self._set_map(town)

    # ---- client API
    def get_client_version(self) -> str:
        return VERSION

    def get_server_version(self) -> str:
        self.check()
        return self.version

    def set_timeout(self, seconds: float) -> None:
        pass

    def get_world(self) -> FakeCarlaServer:
        self.check()
        return self

    def get_available_maps(self) -> list[str]:
        return ["/Game/Carla/Maps/Town01", "/Game/Carla/Maps/Town02"]

    def load_world(self, name: str) -> FakeCarlaServer:
        self.loads.append(name)
        self._set_map(name)
        return self

    def get_trafficmanager(self, port: int) -> Any:
        server = self

        class TM:
            def __getattr__(self, name: str) -> Callable[..., None]:
                return lambda *args: server.tm_calls.append((name, *args))

        return TM()

    # ---- world API
    def check(self) -> None:
        if self.crashed:
            raise RuntimeError("time-out of 10000ms while waiting for the simulator, make sure the simulator is ready")

    def next_id(self) -> int:
        self._id += 1
        return self._id

    def _set_map(self, name: str) -> None:
        self.map = FakeMap(name)
        self.actors = {}
        light = FakeActor(self, "traffic.traffic_light", carla.Transform(), None)
        # the light of the approach the tests drive: the first connector of the central crossing whose lane
        # before it is plain road for 40 m
        centre = carla.Location(x=150.0, y=-150.0, z=0.0)
        self.approach = next(a for a, _ in self.map.real.get_topology() if a.is_junction
                             and a.transform.location.distance(centre) < 20.0
                             and not any(w.is_junction for w in (a.previous(5.0)[0], a.previous(40.0)[0])))
        light.stop_waypoints = [self.approach.previous(3.0)[0]]
        self.actors[light.id] = light
        self.light = light

    def get_map(self) -> FakeMap:
        return self.map

    def get_settings(self) -> carla.WorldSettings:
        s = carla.WorldSettings()
        s.synchronous_mode, s.fixed_delta_seconds = self.settings.synchronous_mode, self.settings.fixed_delta_seconds
        return s

    def apply_settings(self, settings: carla.WorldSettings) -> int:
        self.check()
        self.settings = settings
        self.settings_history.append(settings)
        return self.frame

    def set_weather(self, weather: carla.WeatherParameters) -> None:
        self.weather = weather

    def set_pedestrians_seed(self, seed: int) -> None:
        self.nav_index = seed % len(self.nav_points)

    def get_blueprint_library(self) -> FakeLibrary:
        return FakeLibrary()

    def get_random_location_from_navigation(self) -> carla.Location:
        self.nav_index += 1
        return self.nav_points[self.nav_index % len(self.nav_points)]

    def get_actors(self) -> FakeActorList:
        return FakeActorList(self.actors.values())

    def try_spawn_actor(self, bp: FakeBlueprint, transform: carla.Transform, attach_to: FakeActor | None = None) -> FakeActor | None:
        self.check()
        if attach_to is None and bp.id.startswith("vehicle."):
            for a in self.actors.values():
                if a.type_id.startswith("vehicle.") and a.transform.location.distance(transform.location) < 2.0:
                    return None
        actor = FakeActor(self, bp.id, transform, attach_to)
        self.actors[actor.id] = actor
        if bp.attrs.get("role_name") == "hero":
            self.ego, self.ego_state = actor, EgoState(*convert.pose_from_transform(transform).as_array())
            self.ego_control = Control()
        return actor

    def tick(self, seconds: float = 10.0) -> int:
        self.check()
        self.frame += 1
        if self.ego_state is not None and self.ego.id in self.actors:
            self.ego_state = step_bicycle(self.ego_state, self.ego_control, self.params)
            s = self.ego_state
            self.ego.transform = convert.pose_to_transform(Pose(s.x, s.y, s.yaw), 0.0)
            self.ego.velocity = carla.Vector3D(s.speed * math.cos(s.yaw), -s.speed * math.sin(s.yaw), 0.0)
        self.light.state = carla.TrafficLightState.Red if self.frame < self.light_red_until else carla.TrafficLightState.Green
        for sensor in list(self.actors.values()):
            if sensor.callback is None:
                continue
            if sensor.type_id == "sensor.camera.rgb":
                img = np.zeros((600, 800, 4), dtype=np.uint8)
                img[:, :, 2] = (np.arange(600) % 256)[:, None]
                img[:, :, 1] = self.frame % 256
                sensor.callback(FakeImage(self.frame, img.tobytes()))
            elif sensor.type_id == "sensor.other.collision":
                for other in list(self.actors.values()):
                    if other.type_id.startswith("vehicle.") and other is not self.ego \
                            and other.transform.location.distance(self.ego.transform.location) < 3.0:
                        sensor.callback(FakeCollision(self.frame, other))
        return self.frame


class FakeImage:
    def __init__(self, frame: int, raw: bytes) -> None:
        self.frame, self.raw_data, self.width, self.height = frame, raw, 800, 600


class FakeCollision:
    def __init__(self, frame: int, other: FakeActor) -> None:
        self.frame, self.other_actor = frame, other


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
