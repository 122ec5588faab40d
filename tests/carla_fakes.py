"""`FakeCarlaServer`: a stand-in for the CARLA server, shared by the CARLA tests (no server runs here).

It answers the client calls CarlaWorld makes. Its map is REAL: a carla.Map the client library builds
offline from tests/fixtures/carla/grid.xodr (a 3x3 street grid), so waypoints, topology, junction flags and
off-road queries are CARLA's own. What it fakes: actors, ticking (the ego moves by yawil's kinematic
bicycle), the camera (a BGRA gradient), collisions (ego within 3 m of another vehicle), one traffic light
(red for the first 12 s), the Traffic Manager and walker controllers (recorded, not simulated), and crashes
on demand. Lives in tests/ only; the package never imports it.
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import carla
import numpy as np

from yawil.sim.carla import convert
from yawil.sim.town.dynamics import EgoState, VehicleParams, step_bicycle
from yawil.sim.types import Control, Pose

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
               "sensor.camera.semantic_segmentation", "sensor.other.collision", "sensor.other.lane_invasion"]
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
        self.timeouts: list[float] = []  # every set_timeout, in order
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
        self.timeouts.append(seconds)

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
            elif sensor.type_id == "sensor.camera.semantic_segmentation":
                sensor.callback(FakeImage(self.frame, semantic_frame().tobytes()))
            elif sensor.type_id == "sensor.other.collision":
                for other in list(self.actors.values()):
                    if other.type_id.startswith("vehicle.") and other is not self.ego \
                            and other.transform.location.distance(self.ego.transform.location) < 3.0:
                        sensor.callback(FakeCollision(self.frame, other))
        return self.frame


def semantic_frame() -> np.ndarray:
    """The fake semantic camera's BGRA frame, tags in red: sky over the horizon (row 300), road below, a car
    (rows 320-400, columns 300-500) and a pole (column 100); green and blue hold noise CARLA would not send."""
    tags = carla.CityObjectLabel
    img = np.zeros((600, 800, 4), dtype=np.uint8)
    img[:, :, 0] = 77
    img[:, :, 1] = np.arange(800) % 256
    img[:300, :, 2] = int(tags.Sky)
    img[300:, :, 2] = int(tags.Roads)
    img[320:400, 300:500, 2] = int(tags.Car)
    img[150:450, 96:104, 2] = int(tags.Poles)
    return img


class FakeImage:
    def __init__(self, frame: int, raw: bytes) -> None:
        self.frame, self.raw_data, self.width, self.height = frame, raw, 800, 600


class FakeCollision:
    def __init__(self, frame: int, other: FakeActor) -> None:
        self.frame, self.other_actor = frame, other
