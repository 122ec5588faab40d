"""EmbeddedWorld: the built-in simulator backend (the `World` protocol of yawil.sim.types).

One step: validate the control, move the ego (bicycle model), advance the lights, the vehicles and the
pedestrians, run the criteria, then assemble the observation (rendering the camera only when the scenario
asks for it). Everything random comes from generators spawned from the reset seed, one per concern, so the
same scenario, seed and controls give the same observations bit for bit.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from yawil.sim.criteria import BoxContacts
from yawil.sim.judge import EpisodeJudge
from yawil.sim.town.dynamics import EgoState, VehicleParams, step_bicycle
from yawil.sim.town.map.geometry import ActorView
from yawil.sim.town.map.planner import PlannedRoute, plan_route, random_route
from yawil.sim.town.map.regions import JUNCTION_BASE
from yawil.sim.town.map.town import Town, get_town, lane_heading_at
from yawil.sim.town.traffic.lights import STATE_NAMES, TrafficLights
from yawil.sim.town.traffic.pedestrians import HEIGHT, PED_COLORS, SIZE, Pedestrians
from yawil.sim.town.traffic.vehicles import VEHICLE_COLORS, Vehicles
from yawil.sim.types import (
    COMMAND_LOOKAHEAD,
    DT,
    PRIVILEGED_RADIUS,
    AgentState,
    Control,
    Event,
    LightState,
    Observation,
    Privileged,
    RoadOption,
    Scenario,
    validate_scenario,
)

EGO_ID = 0
EGO_COLOR = (0.15, 0.35, 0.75)
EGO_COMMIT_S = 2.0  # s: traffic treats the ego as in the junction it will reach within this time


class EmbeddedWorld:
    """The embedded backend. `render_backend` is handed to the camera renderer ("software" | "opengl")."""

    def __init__(self, render_backend: str = "software", params: VehicleParams | None = None) -> None:
        self.render_backend = render_backend
        self.params = params or VehicleParams()
        self.town: Town | None = None
        self.scenario: Scenario | None = None
        self._renderer: Any = None
        self._renderer_town: str | None = None
        self.timings: dict[str, float] = {}

    # ---------------------------------------------------------------- episode
    def reset(self, scenario: Scenario, seed: int) -> Observation:
        validate_scenario(scenario)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        town = get_town(scenario.town)
        self.town, self.scenario = town, scenario
        r_route, r_lights, r_veh, r_ped, r_step = (np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(5))
        self._rng = r_step
        if scenario.start is not None and scenario.goal is not None:
            planned = plan_route(town.lanes, scenario.start, scenario.goal)
        else:
            planned = random_route(town.lanes, r_route, scenario.min_route_length, start=scenario.start, goal=scenario.goal)
        self.planned: PlannedRoute = planned
        route = planned.route
        self.route = route
        self.ego = EgoState(float(route.xy[0, 0]), float(route.xy[0, 1]), float(route.lane_yaw[0]))
        self.time, self.frame = 0.0, 0
        self.lights = TrafficLights(town.lanes)
        self.lights.reset(r_lights)
        self.vehicles = Vehicles(town.lanes)
        self.vehicles.spawn(int(scenario.vehicles), r_veh, keep_out=[(self.ego.x, self.ego.y, 15.0)])
        self.pedestrians = Pedestrians(town.walkways)
        self.pedestrians.spawn(int(scenario.pedestrians), r_ped, keep_out=[(self.ego.x, self.ego.y, 4.0)])
        aps = town.lanes.approaches
        self.judge = EpisodeJudge(route, (np.array([a.light for a in aps], dtype=np.int64),
                                          np.array([a.centre_xy for a in aps]), np.array([a.kerb_xy for a in aps]),
                                          np.array([a.yaw for a in aps])), scenario)
        self._light_objs = [[LightState(a.light, name, a.stop_xy[0], a.stop_xy[1], a.yaw) for name in STATE_NAMES]
                            for a in aps]
        self._road_yaw = np.array([ln.evaluate(np.array([0.0]))[1][0] for ln in town.lanes.lanes])
        self._static_cache: tuple[float, float, np.ndarray | None] = (math.inf, math.inf, None)
        self._lights_key: bytes = b""
        self._lights_tuple: tuple[LightState, ...] = ()
        self._names_key: bytes = b""
        self._names: list[str] = []
        self.judge.start(self.ego.x, self.ego.y, self.ego.yaw, self._ego_region())
        self.events: tuple[Event, ...] = ()
        if scenario.camera:
            self._ensure_renderer()
        return self._observe(())

    def step(self, control: Control) -> Observation:
        if self.scenario is None or self.town is None:
            raise RuntimeError("call reset(scenario, seed) before step()")
        if not isinstance(control, Control):
            raise ValueError(f"step needs a Control, got {type(control).__name__}")
        control.validate()
        prev = (self.ego.x, self.ego.y)
        self.ego = step_bicycle(self.ego, control, self.params)
        self.time = round(self.time + DT, 10)
        self.frame += 1
        codes = self.lights.update(self.time)
        ped_road = self.pedestrians.xy[self.pedestrians.on_road] if self.pedestrians.n else np.zeros((0, 2))
        self.vehicles.step(DT, self._rng, codes, (self.ego.x, self.ego.y, self.ego.yaw, self.ego.speed),
                           (self.params.length, self.params.width), self._ego_connectors(), ped_road,
                           self._ego_road_lane(), self._ego_gate())
        veh = self.vehicles
        actors = np.empty((veh.n + 1, 6))
        actors[:-1] = np.stack([veh.x, veh.y, veh.yaw, veh.length, veh.width, veh.v], 1) if veh.n else actors[:0]
        actors[-1] = (self.ego.x, self.ego.y, self.ego.yaw, self.params.length, self.params.width, self.ego.speed)
        self.pedestrians.step(DT, self._rng, actors)
        events = self._criteria(prev)
        return self._observe(tuple(events))

    @property
    def timeout_s(self) -> float:
        """The episode's time budget (the scenario's, or NoCrash's for the route)."""
        return self.judge.timeout_s

    @property
    def done(self) -> bool:
        return self.judge.done

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
            self._renderer_town = None

    # ---------------------------------------------------------------- helpers
    def _ensure_renderer(self) -> None:
        assert self.town is not None
        if self._renderer is not None and self._renderer_town == self.town.name:
            self._renderer.forget_actors()  # a reused renderer starts the episode as a new one would
            return
        self.close()
        from yawil.sim.town.render.renderer import CameraRenderer

        self._renderer = CameraRenderer(self.town.geometry, backend=self.render_backend)
        self._renderer_town = self.town.name

    def ego_box(self) -> tuple[float, float, float, float, float]:
        return (self.ego.x, self.ego.y, self.ego.yaw, self.params.length, self.params.width)

    def _ego_connectors(self) -> np.ndarray:
        """Junction connectors the ego occupies or is committed to, so traffic yields to it.

        In a junction: the connectors within 2.5 m of its centre. Before one: every connector leaving its lane
        once its front bumper will be in the junction within EGO_COMMIT_S at its speed, or could no longer
        stop short of it at traffic's own comfortable deceleration (or is already in it), since nobody can
        tell which way it will turn. Without that, a vehicle waiting at its junction entry pulled out across
        the ego arriving at 3-5 m/s, and each then stood in the other's path for ever (town02 regular routes
        8 and 10: at 3.3 m/s 2 m before the box, stopping distance alone was not enough warning).
        """
        assert self.town is not None
        code = self.town.regions.query_point(self.ego.x, self.ego.y)
        lanes = self.town.lanes
        if code > JUNCTION_BASE:
            lane, s = self._ego_road_lane()
            if lane < 0 or not lanes.is_junction(lanes.lanes[lane].end_node):
                return np.zeros(0, dtype=np.int64)
            along = math.cos(self.ego.yaw - self._road_yaw[lane]) > 0.5  # driving along it, not across
            to_box = lanes.length[lane] - s - self.params.length / 2
            v = max(self.ego.speed, 0.0)
            if along and to_box < max(v * v / (2 * Vehicles.B_COMF), v * EGO_COMMIT_S):
                return np.array(lanes.lanes[lane].successors, dtype=np.int64)
            return np.zeros(0, dtype=np.int64)
        conns = np.array(lanes.node_connectors[JUNCTION_BASE - code], dtype=np.int64)
        m = np.isin(lanes.sample_lane, conns)
        d = np.hypot(lanes.sample_xy[m, 0] - self.ego.x, lanes.sample_xy[m, 1] - self.ego.y)
        return np.unique(lanes.sample_lane[m][d < 2.5])

    def _ego_gate(self) -> tuple[int, bool]:
        """(the road lane its route leaves the junction ahead by, whether it stands at that junction's stop line).

        Standing: slower than 0.5 m/s with its front bumper within 4 m of the stop line (the vehicles' own
        rule). (-1, False) off its route's lanes or with no junction ahead on the lane.
        """
        lane, s = self._ego_road_lane()
        lanes = self.planned.lanes
        i = self.judge.progress.index
        if lane < 0 or int(lanes[i]) != lane or self.town is None:
            return (-1, False)
        later = np.flatnonzero(lanes[i:] != lane)
        if not len(later):
            return (-1, False)
        graph = self.town.lanes
        conn = graph.lanes[int(lanes[i + int(later[0])])]
        if conn.kind != "connector" or not graph.is_junction(conn.node):
            return (-1, False)
        to_line = graph.length[lane] - graph.STOP_BACK - s - self.params.length / 2
        return (conn.exit, bool(self.ego.speed < 0.5 and to_line < 4.0))

    def _ego_road_lane(self) -> tuple[int, float]:
        """(road lane, arc length) under the ego's centre, or (-1, 0) off the road lanes."""
        assert self.town is not None
        code = self.town.regions.query_point(self.ego.x, self.ego.y)
        lanes = self.town.lanes
        if not 0 <= code < lanes.n_road_lanes:
            return (-1, 0.0)
        c = lanes.lanes[code].ctrl
        u = (c[3] - c[0]) / lanes.length[code]
        return (code, float((self.ego.x - c[0, 0]) * u[0] + (self.ego.y - c[0, 1]) * u[1]))

    def _ego_region(self) -> str:
        assert self.town is not None
        reg = self.town.regions
        c, s = math.cos(self.ego.yaw), math.sin(self.ego.yaw)
        hl, hw = self.params.length / 2 - 0.2, self.params.width / 2 - 0.2
        for dx, dy in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw)):
            code = reg.query_point(self.ego.x + c * dx - s * dy, self.ego.y + s * dx + c * dy)
            if JUNCTION_BASE < code < 0:
                return "off_road"
        code = reg.query_point(self.ego.x, self.ego.y)
        if code <= JUNCTION_BASE:
            return "junction"
        if code < 0:
            return "off_road"
        lanes = self.town.lanes
        if code < lanes.n_road_lanes:
            heading = float(self._road_yaw[code])
        else:
            m = lanes.sample_lane == code
            k = int(np.argmin(np.hypot(lanes.sample_xy[m, 0] - self.ego.x, lanes.sample_xy[m, 1] - self.ego.y)))
            heading = float(lanes.sample_yaw[m][k])
        return "lane" if math.cos(self.ego.yaw - heading) >= 0 else "opposite_lane"

    def _near_statics(self, x: float, y: float) -> np.ndarray:
        """Indices of static objects that could touch the ego, from a cache refreshed every 10 m."""
        assert self.town is not None
        cx, cy, cached = self._static_cache
        if cached is None or math.hypot(x - cx, y - cy) > 10.0:
            st = self.town.statics
            cached = np.flatnonzero(np.hypot(st[:, 0] - x, st[:, 1] - y) < self.town.static_radius + 14.0)
            self._static_cache = (x, y, cached)
        return cached

    def _criteria(self, prev: tuple[float, float]) -> list[Event]:
        assert self.town is not None
        ex, ey, t = self.ego.x, self.ego.y, self.time
        veh, ped, town = self.vehicles, self.pedestrians, self.town
        boxes, ids, types = [], [], []
        # candidates: bounding circles that reach the ego's (exact: the box test would reject the others)
        reach = math.hypot(self.params.length / 2, self.params.width / 2)
        if veh.n:
            near = np.flatnonzero(np.hypot(veh.x - ex, veh.y - ey) < np.hypot(veh.length, veh.width) / 2 + reach)
            if len(near):
                boxes.append(np.stack([veh.x[near], veh.y[near], veh.yaw[near], veh.length[near], veh.width[near]], 1))
                ids.append(veh.ids[near])
                types += ["vehicle"] * len(near)
        if ped.n:
            near = np.flatnonzero(np.hypot(ped.xy[:, 0] - ex, ped.xy[:, 1] - ey) < SIZE * math.sqrt(0.5) + reach)
            if len(near):
                boxes.append(np.stack([ped.xy[near, 0], ped.xy[near, 1], ped.yaw[near], np.full(len(near), SIZE),
                                       np.full(len(near), SIZE)], 1))
                ids.append(ped.ids[near])
                types += ["pedestrian"] * len(near)
        near = self._near_statics(ex, ey)
        if len(near):
            st = town.statics
            near = near[np.hypot(st[near, 0] - ex, st[near, 1] - ey) < town.static_radius[near] + reach]
        if len(near):
            boxes.append(town.statics[near])
            ids.append(near)
            types += ["static"] * len(near)
        if boxes:
            contacts = BoxContacts(self.ego_box(), np.concatenate(boxes), np.concatenate(ids), types)
        else:
            contacts = BoxContacts(self.ego_box(), np.zeros((0, 5)), np.zeros(0, dtype=np.int64), [])
        key = self.lights.codes.tobytes()
        if key != self._names_key:  # the names change a few times a minute; rebuilding them each step cost
            self._names_key, self._names = key, [STATE_NAMES[int(c)] for c in self.lights.codes]
        return self.judge.update(t, ex, ey, self.ego.yaw, prev, contacts, lambda _index: self._ego_region(),
                                 self._names)

    def actor_views(self, radius: float = 120.0) -> list[ActorView]:
        """Vehicles and pedestrians near the ego, as the renderers want them."""
        veh, ped = self.vehicles, self.pedestrians
        out: list[ActorView] = []
        ex, ey = self.ego.x, self.ego.y
        for i in np.flatnonzero(np.hypot(veh.x - ex, veh.y - ey) < radius).tolist():
            out.append(ActorView(int(veh.ids[i]), "vehicle", float(veh.x[i]), float(veh.y[i]), float(veh.yaw[i]),
                                 float(veh.length[i]), float(veh.width[i]), float(veh.height[i]),
                                 VEHICLE_COLORS[int(veh.color_index[i])]))
        for i in np.flatnonzero(np.hypot(ped.xy[:, 0] - ex, ped.xy[:, 1] - ey) < radius).tolist():
            out.append(ActorView(int(ped.ids[i]), "pedestrian", float(ped.xy[i, 0]), float(ped.xy[i, 1]),
                                 float(ped.yaw[i]), SIZE, SIZE, HEIGHT, PED_COLORS[int(ped.color_index[i])]))
        return out

    def ego_view(self) -> ActorView:
        p = self.params
        return ActorView(EGO_ID, "vehicle", self.ego.x, self.ego.y, self.ego.yaw, p.length, p.width, p.height, EGO_COLOR)

    def light_states(self) -> dict[int, str]:
        return self.lights.names()

    def _privileged(self, idx: int) -> Privileged:
        assert self.town is not None
        ex, ey = self.ego.x, self.ego.y
        key = self.lights.codes.tobytes()
        if key != self._lights_key:
            self._lights_key = key
            self._lights_tuple = tuple(self._light_objs[i][int(c)] for i, c in enumerate(self.lights.codes))
        lights = self._lights_tuple
        agents: list[AgentState] = []
        veh, ped = self.vehicles, self.pedestrians
        for i in np.flatnonzero(np.hypot(veh.x - ex, veh.y - ey) < PRIVILEGED_RADIUS).tolist():
            agents.append(AgentState(int(veh.ids[i]), "vehicle", float(veh.x[i]), float(veh.y[i]), float(veh.yaw[i]),
                                     float(veh.v[i]), float(veh.length[i]), float(veh.width[i])))
        for i in np.flatnonzero(np.hypot(ped.xy[:, 0] - ex, ped.xy[:, 1] - ey) < PRIVILEGED_RADIUS).tolist():
            agents.append(AgentState(int(ped.ids[i]), "pedestrian", float(ped.xy[i, 0]), float(ped.xy[i, 1]),
                                     float(ped.yaw[i]), float(ped.v[i]), SIZE, SIZE))
        rx, ry = self.route.xy[idx]
        if math.hypot(rx - ex, ry - ey) < 3.0:
            lane_yaw = float(self.route.lane_yaw[idx])
        else:
            lane_yaw = lane_heading_at(self.town, ex, ey, self.ego.yaw)
        return Privileged(lights=lights, agents=tuple(agents), ego_lane_yaw=lane_yaw)

    def _observe(self, events: tuple[Event, ...]) -> Observation:
        assert self.town is not None and self.scenario is not None
        self.events = events
        idx = self.judge.progress.index
        n = len(self.route)
        command = RoadOption(int(self.route.options[min(idx + COMMAND_LOOKAHEAD, n - 1)]))
        image = None
        if self.scenario.camera:
            self._ensure_renderer()
            image = self._renderer.render(self.ego.pose, self.actor_views(), self.light_states(), self.scenario.weather,
                                          self.frame)
        semantic = self._render_semantic() if self.scenario.semantic else None
        return Observation(
            image=image,
            speed=self.ego.speed,
            pose=self.ego.pose,
            route=self.route,
            route_index=idx,
            command=command,
            events=events,
            time=self.time,
            frame=self.frame,
            done=self.done,
            distance_driven=self.judge.distance.total,
            town=self.town.name,
            bounds=self.town.geometry.bounds,
            weather=self.scenario.weather,
            privileged=self._privileged(idx),
            semantic=semantic,
        )

    def _render_semantic(self) -> np.ndarray:
        """The semantic camera's class ids, pixel-aligned with the image (it needs no RGB render)."""
        self._ensure_renderer()
        ids: np.ndarray = self._renderer.render_semantic(self.ego.pose, self.actor_views(), self.light_states())
        return ids
