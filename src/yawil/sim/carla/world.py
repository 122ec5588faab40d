"""CarlaWorld: the `World` protocol of yawil.sim.types on a CARLA server (0.9.11 and later).

One episode: load Town01/Town02 if needed, synchronous mode at 0.1 s, weather, the route planned on the
map's topology (`topology.py`), the ego (vehicle.lincoln.mkz_2017) with the protocol camera (800x600, fov 100,
at (2.0, 0, 1.4), cropped and resized to 200x88; its semantic twin when the scenario asks), collision and lane-invasion sensors, vehicles through the
Traffic Manager and pedestrians with their AI controllers, all seeded. Each step applies the control,
ticks the server once, reads the ego and its sensors, runs yawil's criteria and returns an Observation in
yawil's frame. Any RuntimeError of the client during an episode (lost connection, crashed server,
time-out) is raised as `SimulatorError`; `reconnect()` starts over with a new client.

One class of ~500 lines on purpose: its methods share the client, the spawned actors and the sensor queues
of the episode; the parts that need no server (conversions, topology and planning, infraction geometry,
weather, connection defaults) are already the modules beside it.
"""

from __future__ import annotations

import contextlib
import math
import queue
import re
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np

from yawil.sim.carla.connection import CarlaConnection
from yawil.sim.carla.convert import (
    CAMERA_FOV,
    CAMERA_HEIGHT,
    CAMERA_WIDTH,
    camera_transform,
    carla_tag_values,
    observation_image,
    observation_semantic,
    pose_from_transform,
    pose_to_transform,
    semantic_lut,
    speed_of,
    vehicle_control,
    xy_to_carla,
    yaw_from_carla,
)
from yawil.sim.carla.errors import START_HINT, CarlaSetupError, SimulatorError
from yawil.sim.carla.infractions import (
    SensorContacts,
    classify_region,
    light_state_name,
    stop_line_arrays,
)
from yawil.sim.carla.topology import CarlaRoute, CarlaTopology
from yawil.sim.carla.weather import carla_weather
from yawil.sim.judge import EpisodeJudge
from yawil.sim.types import (
    COMMAND_LOOKAHEAD,
    DT,
    PRIVILEGED_RADIUS,
    AgentState,
    Control,
    Event,
    LightState,
    Observation,
    Pose,
    Privileged,
    RoadOption,
    Scenario,
    validate_scenario,
)

EGO_BLUEPRINT = "vehicle.lincoln.mkz_2017"
SPAWN_CLEARANCE = 15.0  # metres between the ego's start and any vehicle spawn point
SENSOR_TIMEOUT = 10.0  # seconds to wait for the camera frame of a tick
LOAD_TIMEOUT = 60.0  # seconds allowed for loading a map (slower than any other call)
BOUNDS_MARGIN = 10.0
TOWN_RE = re.compile(r"^town(\d{2}(?:_opt)?)$", re.IGNORECASE)


def carla_town(name: str) -> str:
    """yawil's town name (town01, town02, ...) as CARLA's map name (Town01, Town02, ...)."""
    m = TOWN_RE.match(name) if isinstance(name, str) else None
    if m is None:
        raise ValueError(f"town {name!r}: the CARLA backend drives CARLA's own maps; use town01, town02, ... "
                         f"(layout files and 'square' are for the embedded backend)")
    return "Town" + m.group(1).replace("_OPT", "_Opt").replace("_opt", "_Opt")


def check_scenario(sc: Scenario) -> str:
    """Validates a scenario for CARLA (`validate_scenario`, then the map name); returns CARLA's map name."""
    return carla_town(validate_scenario(sc).town)


class CarlaWorld:
    """The CARLA backend. `make_world("carla", host=..., port=..., timeout=...)` builds it.

    `client` is an already-connected client object (tests pass a stand-in); by default one is made from
    host and port. The server's world settings are saved on connect and restored by `close()`.
    """

    def __init__(self, host: str = CarlaConnection.host, port: int = CarlaConnection.port,
                 timeout: float = CarlaConnection.timeout, tm_port: int = 8000,
                 ego_blueprint: str = EGO_BLUEPRINT, client: Any = None) -> None:
        if not isinstance(host, str) or not host:
            raise ValueError(f"host must be a non-empty string, got {host!r}")
        for name, p in (("port", port), ("tm_port", tm_port)):
            if isinstance(p, bool) or not isinstance(p, int) or not 0 < p < 65536:
                raise ValueError(f"{name} must be an integer in 1..65535, got {p!r}")
        if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not (math.isfinite(timeout) and timeout > 0):
            raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
        self.host, self.port, self.timeout, self.tm_port = host, port, float(timeout), tm_port
        self.ego_blueprint = ego_blueprint
        self._given_client = client
        self._client: Any = None
        self._world: Any = None
        self._original_settings: Any = None
        self._actors: list[Any] = []  # everything we spawned, sensors first when destroyed
        self._topologies: dict[str, CarlaTopology] = {}
        self._sem_lut: np.ndarray | None = None  # CARLA tag -> yawil class, from the client's tags on first use
        self.scenario: Scenario | None = None
        self.connect()

    # ------------------------------------------------------------------ connection
    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    def connect(self) -> None:
        """Connect and check versions: CarlaSetupError (naming host:port) when the server is absent or differs."""
        if self._given_client is not None:
            client = self._given_client
        else:
            import carla

            client = carla.Client(self.host, self.port)
            client.set_timeout(self.timeout)
        try:
            server = str(client.get_server_version())
        except RuntimeError as err:
            raise CarlaSetupError(f"no CARLA server answers at {self.address} within {self.timeout:g} s ({err}); "
                                  f"{START_HINT}") from None
        mine = str(client.get_client_version())
        if _version_key(server) != _version_key(mine):
            raise CarlaSetupError(f"CARLA server at {self.address} is version {server} but the client package is {mine}; "
                                  f"install the matching client (`pip install carla=={server}`) or run a {mine} server")
        self._client = client
        self._world = client.get_world()
        if self._original_settings is None:
            self._original_settings = self._world.get_settings()

    def reconnect(self) -> None:
        """After a SimulatorError: forget the episode's actors, connect again (raises CarlaSetupError if down)."""
        self._destroy_actors()
        self.scenario = None
        if self._given_client is None:
            self._client = None
        self.connect()
        self._destroy_actors()

    @contextlib.contextmanager
    def _guard(self, what: str) -> Iterator[None]:
        try:
            yield
        except SimulatorError:
            raise
        except (RuntimeError, queue.Empty) as err:
            self.scenario = None
            raise SimulatorError(f"CARLA at {self.address} failed during {what}: {err or type(err).__name__}") from err

    # ------------------------------------------------------------------ episode
    def reset(self, scenario: Scenario, seed: int) -> Observation:
        town = check_scenario(scenario)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        with self._guard("reset"):
            self._destroy_actors()
            self._load(town)
            world, client = self._world, self._client
            settings = world.get_settings()
            settings.synchronous_mode = True
            settings.fixed_delta_seconds = DT
            world.apply_settings(settings)
            self._tm = client.get_trafficmanager(self.tm_port)
            self._tm.set_synchronous_mode(True)
            self._tm.set_random_device_seed(int(seed))
            if hasattr(world, "set_pedestrians_seed"):
                world.set_pedestrians_seed(int(seed))
            world.set_weather(carla_weather(scenario.weather))
            r_route, r_veh, r_ped = (np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(3))
            topo = self._topology(town)
            if scenario.start is not None and scenario.goal is not None:
                planned = topo.plan(scenario.start, scenario.goal)
            else:
                planned = topo.random_route(r_route, scenario.min_route_length, start=scenario.start, goal=scenario.goal)
            self.scenario, self.topology, self.planned, self.route = scenario, topo, planned, planned.route
            self._spawn_ego(planned, scenario.camera, scenario.semantic)
            self._spawn_vehicles(int(scenario.vehicles), r_veh)
            self._spawn_pedestrians(int(scenario.pedestrians), r_ped)
            self._setup_criteria(planned, scenario)
            self.time, self.frame = 0.0, 0
            self._tick()
            self._walkers_go(r_ped)
            self._prev_xy = (self._pose.x, self._pose.y)
            self.judge.start(self._pose.x, self._pose.y, self._pose.yaw, self._region(0))
            self._drain_collisions()
            return self._observe(())

    def step(self, control: Control) -> Observation:
        if self.scenario is None:
            raise RuntimeError("call reset(scenario, seed) before step()")
        if not isinstance(control, Control):
            raise ValueError(f"step needs a Control, got {type(control).__name__}")
        command = vehicle_control(control)
        with self._guard("step"):
            self._ego.apply_control(command)
            self._tick()
            self.time = round(self.time + DT, 10)
            self.frame += 1
            events = self._criteria()
            return self._observe(tuple(events))

    @property
    def timeout_s(self) -> float:
        """The episode's time budget (the scenario's, or NoCrash's for the route)."""
        return self.judge.timeout_s

    @property
    def done(self) -> bool:
        return self.judge.done

    def close(self) -> None:
        """Destroy our actors and give the server back its settings (asynchronous mode, as we found it)."""
        if self._world is None:
            return
        self._destroy_actors()
        with contextlib.suppress(RuntimeError):
            if getattr(self, "_tm", None) is not None:
                self._tm.set_synchronous_mode(False)
        with contextlib.suppress(RuntimeError):
            if self._original_settings is not None:
                self._world.apply_settings(self._original_settings)
        self.scenario = None

    # ------------------------------------------------------------------ setup helpers
    def _load(self, town: str) -> None:
        current = str(self._world.get_map().name).rsplit("/", 1)[-1]
        if current == town:
            return
        available = [str(m).rsplit("/", 1)[-1] for m in self._client.get_available_maps()]
        if town not in available:
            raise CarlaSetupError(f"CARLA server at {self.address} has no map {town}; it has {', '.join(sorted(available))}")
        self._client.set_timeout(max(self.timeout, LOAD_TIMEOUT))
        try:
            self._world = self._client.load_world(town)
        finally:
            self._client.set_timeout(self.timeout)
        self._topologies.clear()  # a loaded map has new traffic-light actors: the cached stop lines' ids are stale

    def topology_of(self, town: str) -> CarlaTopology:
        """The planner's topology of a CARLA map (Town01, ...), loading it on the server if needed."""
        with self._guard("loading the map"):
            self._load(town)
            return self._topology(town)

    def _topology(self, town: str) -> CarlaTopology:
        if town not in self._topologies:
            lights = list(self._world.get_actors().filter("traffic.traffic_light"))
            self._topologies[town] = CarlaTopology.from_carla_map(self._world.get_map(), lights)
        topo = self._topologies[town]
        self._map = self._world.get_map()
        self._lights = {int(a.id): a for a in self._world.get_actors().filter("traffic.traffic_light")}
        return topo

    def _spawn(self, blueprint: Any, transform: Any, attach_to: Any = None) -> Any:
        actor = self._world.try_spawn_actor(blueprint, transform, attach_to) if attach_to is not None \
            else self._world.try_spawn_actor(blueprint, transform)
        if actor is not None:
            self._actors.append(actor)
        return actor

    def _spawn_ego(self, planned: CarlaRoute, camera: bool, semantic: bool = False) -> None:
        import carla

        lib = self._world.get_blueprint_library()
        bp = lib.find(self.ego_blueprint)
        if bp.has_attribute("role_name"):
            bp.set_attribute("role_name", "hero")
        start = Pose(float(planned.route.xy[0, 0]), float(planned.route.xy[0, 1]), float(planned.route.lane_yaw[0]))
        x, y = xy_to_carla(start.x, start.y)
        wp = self._map.get_waypoint(carla.Location(x=x, y=y, z=0.0))
        z = (float(wp.transform.location.z) if wp is not None else 0.0) + 0.5
        ego = self._spawn(bp, pose_to_transform(start, z))
        if ego is None:
            raise SimulatorError(f"CARLA at {self.address} could not spawn the ego at {start} (the spot is occupied)")
        self._ego = ego
        extent = ego.bounding_box.extent
        self._ego_half = (float(extent.x), float(extent.y))
        self._images: queue.Queue[Any] = queue.Queue()
        self._sem_images: queue.Queue[Any] = queue.Queue()
        self._hits: list[tuple[int, int, str]] = []
        self._hits_lock = threading.Lock()
        self.lane_markings_crossed: list[tuple[int, tuple[str, ...]]] = []
        self._camera = self._sem_camera = None
        for wanted, bp_id, images in ((camera, "sensor.camera.rgb", self._images),
                                      (semantic, "sensor.camera.semantic_segmentation", self._sem_images)):
            if not wanted:
                continue  # the semantic camera only when the scenario asks for it
            cbp = lib.find(bp_id)
            for key, value in (("image_size_x", CAMERA_WIDTH), ("image_size_y", CAMERA_HEIGHT), ("fov", CAMERA_FOV)):
                cbp.set_attribute(key, str(value))
            cam = self._spawn(cbp, camera_transform(), ego)
            if cam is None:
                raise SimulatorError(f"CARLA at {self.address} could not attach the {bp_id} camera")
            cam.listen(images.put)
            if bp_id == "sensor.camera.rgb":
                self._camera = cam
            else:
                self._sem_camera = cam
                if self._sem_lut is None:
                    self._sem_lut = semantic_lut(carla_tag_values())
        col = self._spawn(lib.find("sensor.other.collision"), carla.Transform(), ego)
        lane = self._spawn(lib.find("sensor.other.lane_invasion"), carla.Transform(), ego)
        if col is None or lane is None:
            raise SimulatorError(f"CARLA at {self.address} could not attach the collision/lane-invasion sensors")
        col.listen(self._on_collision)
        lane.listen(self._on_lane_invasion)
        self._sensors = [s for s in (self._camera, self._sem_camera, col, lane) if s is not None]

    def _on_collision(self, event: Any) -> None:
        other = event.other_actor
        with self._hits_lock:
            self._hits.append((int(event.frame), int(other.id), str(other.type_id)))

    def _on_lane_invasion(self, event: Any) -> None:
        self.lane_markings_crossed.append((int(event.frame), tuple(str(m.type) for m in event.crossed_lane_markings)))

    def _spawn_vehicles(self, n: int, rng: np.random.Generator) -> None:
        if n == 0:
            self._traffic: list[Any] = []
            return
        ego_loc = self._ego.get_transform().location
        points = [p for p in self._map.get_spawn_points() if p.location.distance(ego_loc) > SPAWN_CLEARANCE]
        if len(points) < n:
            raise ValueError(f"Scenario.vehicles={n} but map {self._map.name} has only {len(points)} free spawn points")
        bps = sorted((b for b in self._world.get_blueprint_library().filter("vehicle.*")
                      if not b.has_attribute("number_of_wheels") or int(b.get_attribute("number_of_wheels").as_int()) == 4),
                     key=lambda b: str(b.id))
        order = rng.permutation(len(points))
        self._traffic = []
        for i in order.tolist():
            if len(self._traffic) == n:
                break
            bp = bps[int(rng.integers(len(bps)))]
            if bp.has_attribute("role_name"):
                bp.set_attribute("role_name", "autopilot")
            v = self._spawn(bp, points[i])
            if v is not None:
                v.set_autopilot(True, self.tm_port)
                self._traffic.append(v)

    def _spawn_pedestrians(self, n: int, rng: np.random.Generator) -> None:
        import carla

        self._walkers: list[tuple[Any, Any]] = []
        if n == 0:
            return
        lib = self._world.get_blueprint_library()
        bps = sorted(lib.filter("walker.pedestrian.*"), key=lambda b: str(b.id))
        ctrl_bp = lib.find("controller.ai.walker")
        for _ in range(10 * n):
            if len(self._walkers) == n:
                break
            loc = self._world.get_random_location_from_navigation()
            if loc is None:
                continue
            bp = bps[int(rng.integers(len(bps)))]
            if bp.has_attribute("is_invincible"):
                bp.set_attribute("is_invincible", "false")
            walker = self._spawn(bp, carla.Transform(carla.Location(x=loc.x, y=loc.y, z=loc.z + 1.0)))
            if walker is None:
                continue
            ctrl = self._spawn(ctrl_bp, carla.Transform(), walker)
            if ctrl is not None:
                self._walkers.append((walker, ctrl))
        if len(self._walkers) < n:
            raise SimulatorError(f"CARLA at {self.address} placed only {len(self._walkers)} of {n} pedestrians")

    def _walkers_go(self, rng: np.random.Generator) -> None:
        for _, ctrl in self._walkers:
            ctrl.start()
            ctrl.go_to_location(self._world.get_random_location_from_navigation())
            ctrl.set_max_speed(float(rng.uniform(1.0, 1.6)))

    def _setup_criteria(self, planned: CarlaRoute, sc: Scenario) -> None:
        self.judge = EpisodeJudge(planned.route, stop_line_arrays(self.topology.stops), sc)
        b = self.topology.bounds
        self.bounds = (b[0] - BOUNDS_MARGIN, b[1] - BOUNDS_MARGIN, b[2] + BOUNDS_MARGIN, b[3] + BOUNDS_MARGIN)

    def _destroy_actors(self) -> None:
        """Stop and destroy what we spawned; actors the server could not be asked about stay listed, so a
        reconnect or the next reset destroys them (after a crash they are gone and destroy() says False)."""
        for s in getattr(self, "_sensors", []):
            with contextlib.suppress(RuntimeError):
                s.stop()
        for ctrl in [c for _, c in getattr(self, "_walkers", [])]:
            with contextlib.suppress(RuntimeError):
                ctrl.stop()
        left = []
        for a in reversed(self._actors):
            try:
                a.destroy()
            except RuntimeError:
                left.append(a)
        self._actors, self._sensors, self._walkers, self._traffic = left[::-1], [], [], []

    # ------------------------------------------------------------------ per step
    def _tick(self) -> None:
        self._server_frame = int(self._world.tick(self.timeout))
        self._pose = pose_from_transform(self._ego.get_transform())
        self._speed = speed_of(self._ego.get_velocity())
        self._image: Any = None
        self._sem_image: Any = None
        if self._camera is not None:
            self._image = self._frame_of(self._images)
        if getattr(self, "_sem_camera", None) is not None:
            self._sem_image = self._frame_of(self._sem_images)

    def _frame_of(self, images: queue.Queue[Any]) -> Any:
        """The camera image of this tick (older ones, left from before a reset, are dropped)."""
        while True:
            img = images.get(timeout=SENSOR_TIMEOUT)
            if int(img.frame) >= self._server_frame:
                return img

    def _drain_collisions(self) -> list[tuple[int, str]]:
        with self._hits_lock:
            hits = [(oid, tid) for f, oid, tid in self._hits if f <= self._server_frame]
            self._hits = [h for h in self._hits if h[0] > self._server_frame]
        return hits

    def _region(self, route_index: int) -> str:
        """Where the ego is (LaneInvasionCriterion.REGIONS), given its projection on the route."""
        import carla

        p = self._pose
        c, s = math.cos(p.yaw), math.sin(p.yaw)
        hl, hw = self._ego_half[0] - 0.2, self._ego_half[1] - 0.2
        driving = carla.LaneType.Driving
        for dx, dy in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw)):
            x, y = xy_to_carla(p.x + c * dx - s * dy, p.y + s * dx + c * dy)
            if self._map.get_waypoint(carla.Location(x=x, y=y, z=0.0), project_to_road=False, lane_type=driving) is None:
                return "off_road"
        x, y = xy_to_carla(p.x, p.y)
        wp = self._map.get_waypoint(carla.Location(x=x, y=y, z=0.0), project_to_road=False, lane_type=driving)
        if wp is None:
            return "off_road"
        i = route_index
        return classify_region(True, bool(wp.is_junction), int(wp.road_id), int(wp.lane_id),
                               yaw_from_carla(wp.transform.rotation.yaw), p.yaw, int(self.planned.road[i]),
                               int(self.planned.lane[i]))

    def _light_names(self) -> list[str]:
        return [light_state_name(self._lights[s.light_id].get_state()) if s.light_id in self._lights else "green"
                for s in self.topology.stops]

    def _criteria(self) -> list[Event]:
        p = self._pose
        contacts = SensorContacts(tuple(self._drain_collisions()))
        events = self.judge.update(self.time, p.x, p.y, p.yaw, self._prev_xy, contacts, self._region,
                                   self._light_names())
        self._prev_xy = (p.x, p.y)
        return events

    def _privileged(self, idx: int) -> Privileged:
        import carla

        p = self._pose
        first: dict[int, Any] = {}
        for s in self.topology.stops:
            first.setdefault(s.light_id, s)
        lights = tuple(LightState(lid, light_state_name(self._lights[lid].get_state()) if lid in self._lights else "green",
                                  s.x, s.y, s.yaw) for lid, s in first.items())
        agents: list[AgentState] = []
        ego_id = int(self._ego.id)
        for a in self._world.get_actors():
            tid = str(a.type_id)
            kind = "vehicle" if tid.startswith("vehicle.") else "pedestrian" if tid.startswith("walker.pedestrian") else None
            if kind is None or int(a.id) == ego_id:
                continue
            q = pose_from_transform(a.get_transform())
            if math.hypot(q.x - p.x, q.y - p.y) >= PRIVILEGED_RADIUS:
                continue
            ext = a.bounding_box.extent
            agents.append(AgentState(int(a.id), kind, q.x, q.y, q.yaw, speed_of(a.get_velocity()), 2 * float(ext.x), 2 * float(ext.y)))
        rx, ry = self.route.xy[idx]
        if math.hypot(rx - p.x, ry - p.y) < 3.0:
            lane_yaw = float(self.route.lane_yaw[idx])
        else:
            x, y = xy_to_carla(p.x, p.y)
            wp = self._map.get_waypoint(carla.Location(x=x, y=y, z=0.0))
            lane_yaw = p.yaw if wp is None else yaw_from_carla(wp.transform.rotation.yaw)
            if math.cos(lane_yaw - p.yaw) < 0.0:
                lane_yaw = math.remainder(lane_yaw + math.pi, 2 * math.pi)
        return Privileged(lights=lights, agents=tuple(agents), ego_lane_yaw=lane_yaw)

    def _observe(self, events: tuple[Event, ...]) -> Observation:
        assert self.scenario is not None
        idx = self.judge.progress.index
        command = RoadOption(int(self.route.options[min(idx + COMMAND_LOOKAHEAD, len(self.route) - 1)]))
        image = observation_image(self._image) if self._image is not None else None
        semantic = None
        if self._sem_image is not None and self._sem_lut is not None:
            semantic = observation_semantic(self._sem_image, self._sem_lut)
        return Observation(
            image=image, speed=self._speed, pose=self._pose, route=self.route, route_index=idx, command=command,
            events=events, time=self.time, frame=self.frame, done=self.done, distance_driven=self.judge.distance.total,
            town=self.scenario.town, bounds=self.bounds, weather=self.scenario.weather, privileged=self._privileged(idx),
            semantic=semantic,
        )


def _version_key(version: str) -> str:
    """'0.9.16', '0.9.16-dirty' and '0.9.16.post1' compare equal: major.minor.patch only."""
    m = re.match(r"\s*(\d+)\.(\d+)\.(\d+)", version)
    return ".".join(m.groups()) if m else version.strip()
