"""Gymnasium wrapper of the embedded world: `gymnasium.make("yawil/Town01-v0")` (also Town02, Square).

Observation: Dict(image uint8 (88, 200, 3) when the camera is on, speed (1,), command Discrete(4) as the
branch index of `yawil.sim.types.COMMANDS`, pose (x, y, yaw)). Action: Box([-1, 0, 0], [1, 1, 1]) =
(steer, throttle, brake), CARLA convention.

Reward per step = metres of route progress - 50 per collision - 5 per lane invasion - 20 per red light.
`terminated` when the goal is reached (or at a collision if terminate_on_collision); `truncated` at the
timeout.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from yawil.sim.town.world import EmbeddedWorld
from yawil.sim.types import Control, EventKind, Observation, Scenario, command_index

PENALTIES = {EventKind.COLLISION: 50.0, EventKind.LANE_INVASION: 5.0, EventKind.RED_LIGHT: 20.0}


class YawilDriveEnv(gym.Env[dict[str, Any], np.ndarray]):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, town: str = "town01", weather: str = "ClearNoon", vehicles: int = 0, pedestrians: int = 0,
                 camera: bool = True, timeout_s: float | None = None, min_route_length: float = 100.0,
                 terminate_on_collision: bool = True, render_mode: str | None = None,
                 render_backend: str = "software") -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode {render_mode!r} is not supported; choose None or 'rgb_array'")
        self.scenario = Scenario(town=town, weather=weather, vehicles=vehicles, pedestrians=pedestrians,
                                 camera=camera, timeout_s=timeout_s, min_route_length=min_route_length)
        self.terminate_on_collision = terminate_on_collision
        self.render_mode = render_mode
        self.world = EmbeddedWorld(render_backend=render_backend)
        obs_spaces: dict[str, spaces.Space[Any]] = {
            "speed": spaces.Box(0.0, 100.0, shape=(1,), dtype=np.float32),
            "command": spaces.Discrete(4),
            "pose": spaces.Box(np.array([-1e5, -1e5, -np.pi], dtype=np.float32),
                               np.array([1e5, 1e5, np.pi], dtype=np.float32), dtype=np.float32),
        }
        if camera:
            obs_spaces["image"] = spaces.Box(0, 255, shape=(88, 200, 3), dtype=np.uint8)
        self.observation_space = spaces.Dict(obs_spaces)
        self.action_space = spaces.Box(np.array([-1.0, 0.0, 0.0], dtype=np.float32),
                                       np.array([1.0, 1.0, 1.0], dtype=np.float32), dtype=np.float32)
        self._last: Observation | None = None
        self._progress = 0.0

    def _convert(self, obs: Observation) -> dict[str, Any]:
        out: dict[str, Any] = {
            "speed": np.array([min(obs.speed, 100.0)], dtype=np.float32),
            "command": command_index(int(obs.command)),
            "pose": np.array([obs.pose.x, obs.pose.y, obs.pose.yaw], dtype=np.float32),
        }
        if self.scenario.camera:
            out["image"] = obs.image
        return out

    def _info(self, obs: Observation) -> dict[str, Any]:
        return {"events": obs.events, "route_index": obs.route_index, "time": obs.time,
                "distance_driven": obs.distance_driven}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        episode_seed = int(self.np_random.integers(0, 2**31 - 1))
        obs = self.world.reset(self.scenario, episode_seed)
        self._last = obs
        self._progress = self.world.c_progress.progress
        return self._convert(obs), self._info(obs)

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (3,):
            raise ValueError(f"action must be (steer, throttle, brake), got shape {np.shape(action)}")
        obs = self.world.step(Control(float(a[0]), float(a[1]), float(a[2])))
        self._last = obs
        progress = self.world.c_progress.progress
        reward = progress - self._progress - sum(PENALTIES.get(e.kind, 0.0) for e in obs.events)
        self._progress = progress
        kinds = {e.kind for e in obs.events}
        terminated = self.world.c_goal.reached or (self.terminate_on_collision and EventKind.COLLISION in kinds)
        truncated = self.world.c_timeout.expired and not terminated
        return self._convert(obs), float(reward), bool(terminated), bool(truncated), self._info(obs)

    @property
    def last_observation(self) -> Observation | None:
        """The full simulator observation of the last step (route, privileged state, events)."""
        return self._last

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        if self.render_mode != "rgb_array" or self._last is None:
            return None
        return self._last.image

    def close(self) -> None:
        self.world.close()
