"""Gymnasium wrapper of the embedded world: `gymnasium.make("yawil/Town01-v0")` (also Town02, Square).

It sits above the simulator, not in it (docs/architecture.md): it adds the guidance vector and the expert's
action to what the world gives.

`import yawil` registers the ids (see `yawil.__init__`); the entry point is `make_env` below, which checks
the options and builds `YawilDriveEnv`.

Observation: Dict(
  image uint8 (88, 200, 3) when the camera is on (the models' main input),
  speed (1,) m/s, command Discrete(4) = branch index of `yawil.sim.types.COMMANDS`, pose (x, y, yaw),
  route (K+1, 2): the route ahead in map metres, one point every `spacing` metres from the ego's projection,
  route_ego (K+1, 2): the same points in the car's frame (x forward, y left, metres): what a learned policy
  that should not depend on where in the town it is wants,
  guidance (K,) (or (2K,) for "xy"): the paper's guidance vector, from `yawil.guidance.compute_guidance`,
)
with K and spacing from `guidance_config` (default 15 points, 2 m). `guidance=None` drops `route` and
`guidance` (the observation before they were added). Action: Box([-1, 0, 0], [1, 1, 1]) = (steer, throttle,
brake), CARLA convention.

Reward per step = metres of route progress (the ego's continuous projection on the route, so it is ~0.5 a
step at 5 m/s, and negative when backing up) - 50 per collision - 5 per lane invasion - 20 per red light.
`terminated` when the goal is reached (or at a collision, unless terminate_on_collision=False); `truncated` at
the timeout. `info["success"]` (the goal reached) and `info["reason"]` (None while the episode runs; then
"goal", "collision_vehicle" / "collision_pedestrian" / "collision_static" or "timeout") say how it ended, as
the benchmark names it. An action outside the Box is clipped to it (a non-finite one is refused), as the
simulator clips controls.

To drive with a trained agent, give it the simulator observation the env keeps: `agent.act(env.unwrapped.
last_observation)` (`yawil.agent.gym_action(agent, env)`): the agent computes its own guidance the way its model
was trained (its checkpoint's reference), whatever this env's `guidance_config` is. With `expert_action=True` (or reset option {"expert_action": True}) `info["expert_action"]` holds
what the privileged expert (`yawil.expert.Expert`) would do for the returned observation, as float32
(steer, throttle, brake): the label imitation learning (and DAgger) needs.

Rendering is headless: `render_mode="rgb_array"` gives a bird's-eye image of the town (roads, route, lights,
agents, the ego and its trail); "human" is refused with a ValueError, as no window can be opened here.
"""

from __future__ import annotations

import difflib
import inspect
import math
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from yawil.expert import Expert
from yawil.guidance import GUIDANCE_KINDS, GuidanceConfig, compute_guidance, project_on_route, resample_route
from yawil.sim.route_geometry import arc_lengths
from yawil.sim.town.map.layout import resolve_town
from yawil.sim.town.render.renderer import BACKENDS as RENDER_BACKENDS
from yawil.sim.town.world import EmbeddedWorld
from yawil.sim.types import Control, EventKind, Observation, Scenario, command_index, validate_scenario

PENALTIES = {EventKind.COLLISION: 50.0, EventKind.LANE_INVASION: 5.0, EventKind.RED_LIGHT: 20.0}
RENDER_MODES: tuple[str, ...] = ("rgb_array",)
RESET_OPTIONS: tuple[str, ...] = ("expert_action",)
COORD_LIMIT = 1e5  # metres: bound of the map-frame Boxes (pose, route)
ACTION_LOW = np.array([-1.0, 0.0, 0.0], dtype=np.float32)  # steer, throttle, brake (CARLA's ranges)
ACTION_HIGH = np.array([1.0, 1.0, 1.0], dtype=np.float32)


def _render_mode_error(mode: object) -> ValueError:
    """One line that says why a mode is refused and which ones work (shared by make_env and the class)."""
    if mode == "human":
        return ValueError("render_mode='human' is not supported: the yawil environments are headless (no window); "
                          "use render_mode='rgb_array' for a bird's-eye image "
                          "(or 'rgb_array_list' via gymnasium.make), "
                          "or None")
    return ValueError(f"render_mode {mode!r} is not supported; choose None, 'rgb_array' or "
                      "'rgb_array_list' (the last via gymnasium.make)")


def _flag(name: str, value: Any) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


class YawilDriveEnv(gym.Env[dict[str, Any], np.ndarray]):
    """One embedded-world episode per `reset`; seeded resets replay the same episode."""

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": 10}

    def __init__(self, town: str = "town01", weather: str = "ClearNoon", vehicles: int = 0, pedestrians: int = 0,
                 camera: bool = True, timeout_s: float | None = None, min_route_length: float = 100.0,
                 terminate_on_collision: bool = True, render_mode: str | None = None,
                 render_backend: str = "software", guidance: str | None = "yaw",
                 guidance_config: GuidanceConfig | Mapping[str, Any] | None = None,
                 expert_action: bool = False) -> None:
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise _render_mode_error(render_mode)
        if not isinstance(town, str) or not town:
            raise ValueError(f"town must be a town name or a layout .json path, got {town!r}")
        resolve_town(town)  # an unknown town fails here, not at the first reset
        camera = _flag("camera", camera)
        self.terminate_on_collision = _flag("terminate_on_collision", terminate_on_collision)
        self.expert_action = _flag("expert_action", expert_action)
        if not isinstance(render_backend, str) or render_backend not in RENDER_BACKENDS:  # else refused at reset()
            raise ValueError(f"render_backend must be one of {', '.join(map(repr, RENDER_BACKENDS))}, "
                             f"got {render_backend!r}")
        if guidance is not None and guidance not in GUIDANCE_KINDS:
            kinds = ", ".join(map(repr, GUIDANCE_KINDS))
            raise ValueError(f"guidance must be one of {kinds} or None, got {guidance!r}")
        if guidance_config is None:
            guidance_config = GuidanceConfig()
        elif isinstance(guidance_config, Mapping):
            guidance_config = GuidanceConfig.from_dict(guidance_config)
        elif not isinstance(guidance_config, GuidanceConfig):
            raise ValueError("guidance_config must be a GuidanceConfig, a mapping of its fields "
                             f"(spacing, count, reference) or None, got {type(guidance_config).__name__}")
        self.scenario = Scenario(town=town, weather=weather, vehicles=vehicles, pedestrians=pedestrians,
                                 camera=camera, timeout_s=timeout_s, min_route_length=min_route_length)
        validate_scenario(self.scenario)  # weather, counts, timeout, route length: clear errors before any reset
        self.guidance = guidance
        self.guidance_config = guidance_config
        self.render_mode = render_mode
        self.world = EmbeddedWorld(render_backend=render_backend)
        k = guidance_config.count
        obs_spaces: dict[str, spaces.Space[Any]] = {
            "speed": spaces.Box(0.0, 100.0, shape=(1,), dtype=np.float32),
            "command": spaces.Discrete(4),
            "pose": spaces.Box(np.array([-COORD_LIMIT, -COORD_LIMIT, -np.pi], dtype=np.float32),
                               np.array([COORD_LIMIT, COORD_LIMIT, np.pi], dtype=np.float32), dtype=np.float32),
        }
        if guidance is not None:
            obs_spaces["route"] = spaces.Box(-COORD_LIMIT, COORD_LIMIT, shape=(k + 1, 2), dtype=np.float32)
            obs_spaces["route_ego"] = spaces.Box(-COORD_LIMIT, COORD_LIMIT, shape=(k + 1, 2), dtype=np.float32)
            if guidance == "xy":
                obs_spaces["guidance"] = spaces.Box(-1.0, 1.0, shape=(2 * k,), dtype=np.float32)
            else:
                obs_spaces["guidance"] = spaces.Box(-np.pi, np.pi, shape=(k,), dtype=np.float32)
        if camera:
            obs_spaces["image"] = spaces.Box(0, 255, shape=(88, 200, 3), dtype=np.uint8)
        self.observation_space = spaces.Dict(obs_spaces)
        self.action_space = spaces.Box(ACTION_LOW, ACTION_HIGH, dtype=np.float32)
        self._last: Observation | None = None
        self._progress = 0.0
        self._progress_hint: int | None = None  # route segment of the last progress projection
        self._reason: str | None = None
        self._hint: int | None = None  # route segment of the last guidance, as the data collector keeps it
        self._expert: Expert | None = None
        self._label = False  # whether this episode's info carries the expert's action
        self._birdseye: _BirdsEye | None = None
        self._trail: list[tuple[float, float]] = []  # the ego's positions this episode, for the render

    # ------------------------------------------------------------------------------------- observation
    def _convert(self, obs: Observation) -> dict[str, Any]:
        out: dict[str, Any] = {
            "speed": np.array([min(max(obs.speed, 0.0), 100.0)], dtype=np.float32),
            "command": command_index(int(obs.command)),
            "pose": np.array([obs.pose.x, obs.pose.y, obs.pose.yaw], dtype=np.float32),
        }
        if self.guidance is not None:
            cfg = self.guidance_config
            route = obs.route
            g, self._hint = compute_guidance(route.xy, route.lane_yaw, (obs.pose.x, obs.pose.y), obs.pose.yaw,
                                             obs.bounds, cfg, hint_index=self._hint)
            _, s = project_on_route(route.xy, (obs.pose.x, obs.pose.y), hint_index=self._hint)
            # the K+1 points the yaw guidance is built from: heading differences of `route` give `guidance`
            points = resample_route(route.xy, s, cfg.spacing, cfg.count + 1)
            out["route"] = np.clip(points, -COORD_LIMIT, COORD_LIMIT).astype(np.float32)
            c, si = np.cos(obs.pose.yaw), np.sin(obs.pose.yaw)
            d = points - np.array([obs.pose.x, obs.pose.y])
            ego = np.column_stack((c * d[:, 0] + si * d[:, 1], -si * d[:, 0] + c * d[:, 1]))
            out["route_ego"] = np.clip(ego, -COORD_LIMIT, COORD_LIMIT).astype(np.float32)
            out["guidance"] = np.array(g.get(self.guidance), dtype=np.float32)  # a writable copy
        if self.scenario.camera:
            out["image"] = obs.image
        return out

    def _route_s(self, obs: Observation) -> float:
        """Metres along the route of the ego's projection (continuous, unlike the judge's 1 m route points)."""
        self._progress_hint, s = project_on_route(obs.route.xy, (obs.pose.x, obs.pose.y), hint_index=self._progress_hint)
        return s

    def _info(self, obs: Observation) -> dict[str, Any]:
        info: dict[str, Any] = {"events": obs.events, "route_index": obs.route_index, "time": obs.time,
                                "distance_driven": obs.distance_driven,
                                "success": bool(self.world.judge.goal.reached), "reason": self._reason}
        if self._label:
            assert self._expert is not None
            c = self._expert.act(obs)
            info["expert_action"] = np.array([c.steer, c.throttle, c.brake], dtype=np.float32)
        return info

    # --------------------------------------------------------------------------------------- episodes
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        """Start an episode; the world's seed is drawn from `np_random`, so one seed gives one episode."""
        label = self.expert_action
        if options is not None:
            if not isinstance(options, Mapping):
                raise ValueError(f"reset options must be a dict or None, got {type(options).__name__}")
            unknown = sorted(set(options) - set(RESET_OPTIONS))
            if unknown:
                raise ValueError(f"unknown reset option(s) {unknown}; known: {', '.join(RESET_OPTIONS)}")
            if "expert_action" in options:
                label = _flag("reset option expert_action", options["expert_action"])
        super().reset(seed=seed)
        episode_seed = int(self.np_random.integers(0, 2**31 - 1))
        obs = self.world.reset(self.scenario, episode_seed)
        self._last = obs
        self._progress_hint, self._reason = None, None
        self._progress = self._route_s(obs)
        self._hint = None
        self._label = label
        if label:
            self._expert = self._expert or Expert()
            self._expert.reset()
        self._trail = [(obs.pose.x, obs.pose.y)]
        if self._birdseye is not None:
            self._birdseye.start(obs)
        return self._convert(obs), self._info(obs)

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        if self._last is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (3,):
            raise ValueError(f"action must be (steer, throttle, brake), got shape {np.shape(action)}")
        if not np.isfinite(a).all():
            raise ValueError(f"action must be finite (steer, throttle, brake), got {a.tolist()}")
        a = np.clip(a, ACTION_LOW, ACTION_HIGH)
        obs = self.world.step(Control(float(a[0]), float(a[1]), float(a[2])))
        self._last = obs
        progress = self._route_s(obs)
        reward = progress - self._progress - sum(PENALTIES.get(e.kind, 0.0) for e in obs.events)
        self._progress = progress
        collision = next((e for e in obs.events if e.kind == EventKind.COLLISION), None)
        terminated = self.world.judge.goal.reached or (self.terminate_on_collision and collision is not None)
        truncated = self.world.judge.timeout.expired and not terminated
        if self._reason is None:
            if self.world.judge.goal.reached:
                self._reason = "goal"
            elif collision is not None and terminated:
                self._reason = f"collision_{collision.other_type or 'static'}"
            elif truncated:
                self._reason = "timeout"
        if self.render_mode is not None:
            self._trail.append((obs.pose.x, obs.pose.y))
        return self._convert(obs), float(reward), bool(terminated), bool(truncated), self._info(obs)

    @property
    def last_observation(self) -> Observation | None:
        """The full simulator observation of the last step (route, privileged state, events)."""
        return self._last

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        """The bird's-eye image (H, W, 3) uint8 in "rgb_array" mode; None without a render mode."""
        if self.render_mode is None:
            return None
        if self._last is None:
            raise gym.error.ResetNeeded("call reset() before render()")
        if self._birdseye is None:  # drawn on first use, so envs that never render never load matplotlib
            assert self.world.town is not None
            self._birdseye = _BirdsEye(self.world.town.geometry)
            self._birdseye.start(self._last)
        return self._birdseye.frame(self.world, self._trail)

    def close(self) -> None:
        self.world.close()
        self._birdseye = None


def make_env(**kwargs: Any) -> gym.Env[dict[str, Any], np.ndarray]:
    """The registered entry point: one clear ValueError for a misspelt option or an unsupported render mode.

    `gymnasium.make` would otherwise wrap 'human' in its pygame window (a crash on a headless machine) and turn
    an unknown option into a TypeError about the constructor; 'rgb_array_list' gets gymnasium's RenderCollection.
    """
    known = [p for p in inspect.signature(YawilDriveEnv.__init__).parameters if p != "self"]
    for name in kwargs:
        if name not in known:
            close = difflib.get_close_matches(name, known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ValueError(f"unknown option {name!r} for the yawil environments{hint}; known: {', '.join(known)}")
    mode = kwargs.get("render_mode")
    if mode == "rgb_array_list":
        from gymnasium.wrappers import RenderCollection

        return RenderCollection(YawilDriveEnv(**{**kwargs, "render_mode": "rgb_array"}))
    if mode is not None and mode not in RENDER_MODES:
        raise _render_mode_error(mode)
    return YawilDriveEnv(**kwargs)


# ---------------------------------------------------------------------------------------------- bird's-eye
_TRAIL = (255, 140, 0)
_EGO = (255, 45, 149)  # the ego's colour in draw_birdseye
_ROUTE = (31, 95, 255)
_LIGHTS = {"red": (224, 32, 32), "yellow": (240, 192, 32), "green": (32, 192, 64)}


class _BirdsEye:
    """The town drawn once by `draw_birdseye` (the project's map), then per frame a few pixels painted on a copy.

    A full matplotlib draw costs about 0.3 s; painting the route, lights, agents and ego on cached pixels costs
    well under a millisecond, so rendering every step stays cheap.
    """

    SIZE = 480  # pixels along the town's longer side

    def __init__(self, geometry: Any) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        from yawil.sim.town.render.birdseye import draw_birdseye

        self.geometry = geometry
        xmin, ymin, xmax, ymax = geometry.bounds
        span = max(xmax - xmin, ymax - ymin)
        dpi = 100
        fig = Figure(figsize=(self.SIZE * (xmax - xmin) / span / dpi, self.SIZE * (ymax - ymin) / span / dpi), dpi=dpi)
        canvas = FigureCanvasAgg(fig)
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        draw_birdseye(geometry, ax=ax)
        ax.set_title("")
        ax.set_axis_off()
        canvas.draw()
        self.background = np.ascontiguousarray(np.asarray(canvas.buffer_rgba())[..., :3])
        self.matrix = np.array(ax.transData.get_matrix())  # map metres -> display pixels (origin bottom left)
        self.px_per_m = float(self.matrix[0, 0])
        self._episode = self.background

    def _display(self, xy: Any) -> np.ndarray:
        """(N, 2) map points -> (N, 2) display coordinates (pixels, origin at the bottom left)."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return np.asarray(pts @ self.matrix[:2, :2].T + self.matrix[:2, 2])

    def _px(self, xy: Any) -> np.ndarray:
        """(N, 2) map points -> (N, 2) integer (row, column) pixels."""
        disp = self._display(xy)
        rows = self.background.shape[0] - 1 - np.floor(disp[:, 1])
        return np.column_stack((rows, np.floor(disp[:, 0]))).astype(np.int64)

    def _dots(self, img: np.ndarray, rc: np.ndarray, color: tuple[int, int, int], r: int) -> None:
        h, w = img.shape[:2]
        for row, col in rc.tolist():
            img[max(0, row - r) : min(h, row + r + 1), max(0, col - r) : min(w, col + r + 1)] = color

    def _box(self, img: np.ndarray, x: float, y: float, yaw: float, length: float, width: float,
             color: tuple[int, int, int]) -> None:
        """Fill a rotated rectangle (at least a 3x3 pixel block, so small things stay visible)."""
        ppm = self.px_per_m
        half = 0.5 * math.hypot(length, width) * ppm + 2
        (dx0, dy0), = self._display([x, y]).tolist()
        h, w = img.shape[:2]
        row, col = h - dy0, dx0  # fractional pixel position, rows counted from the top
        r0, r1 = max(0, int(row - half)), min(h, int(row + half) + 1)
        c0, c1 = max(0, int(col - half)), min(w, int(col + half) + 1)
        if r0 >= r1 or c0 >= c1:
            return
        rr, cc = np.mgrid[r0:r1, c0:c1]
        dx, dy = (cc + 0.5 - dx0) / ppm, (h - rr - 0.5 - dy0) / ppm  # pixel centres relative to (x, y), metres
        c, s = math.cos(yaw), math.sin(yaw)
        u, v = c * dx + s * dy, -s * dx + c * dy
        inside = (np.abs(u) <= max(0.5 * length, 1.5 / ppm)) & (np.abs(v) <= max(0.5 * width, 1.5 / ppm))
        img[r0:r1, c0:c1][inside] = color

    def start(self, obs: Observation) -> None:
        """A new episode: paint its route once onto a copy of the map."""
        img = self.background.copy()
        route = np.asarray(obs.route.xy, dtype=np.float64)
        _, s = arc_lengths(route)
        fine = np.linspace(0.0, s[-1], max(2, int(s[-1] * self.px_per_m * 2) + 1))  # half-pixel steps: no gaps
        dense = np.column_stack((np.interp(fine, s, route[:, 0]), np.interp(fine, s, route[:, 1])))
        self._dots(img, self._px(dense), _ROUTE, 1)
        self._episode = img

    def frame(self, world: EmbeddedWorld, trail: list[tuple[float, float]]) -> np.ndarray:
        """This step's image: the episode's map, the ego's trail, light states, agents and the ego."""
        img = self._episode.copy()
        if trail:
            self._dots(img, np.unique(self._px(trail), axis=0), _TRAIL, 0)
        states = world.light_states()
        for lp in self.geometry.light_posts:
            color = _LIGHTS.get(states.get(lp.id, ""))
            if color is not None:
                self._dots(img, self._px(np.array([lp.x, lp.y])), color, 2)
        from matplotlib.colors import to_rgb

        for a in world.actor_views(radius=math.inf):
            rgb = tuple(int(round(255 * v)) for v in to_rgb(a.color))
            self._box(img, a.x, a.y, a.yaw, a.length, a.width, (rgb[0], rgb[1], rgb[2]))
        ego = world.ego_view()
        self._box(img, ego.x, ego.y, ego.yaw, ego.length, ego.width, _EGO)
        nose = np.array([[ego.x + d * math.cos(ego.yaw), ego.y + d * math.sin(ego.yaw)]
                         for d in np.linspace(0.0, 6.0, 13)])
        self._dots(img, self._px(nose), _EGO, 0)
        return img
