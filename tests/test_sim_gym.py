"""The Gymnasium environments registered by yawil.sim."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import yawil.sim  # noqa: F401  (registers the environments)
from yawil.sim.gym_env import YawilDriveEnv


def test_registered_and_passes_check_env() -> None:
    for env_id in ("yawil/Town01-v0", "yawil/Town02-v0", "yawil/Square-v0"):
        assert env_id in gymnasium.registry
    env = gymnasium.make("yawil/Square-v0", camera=False, vehicles=3, pedestrians=3)
    check_env(env.unwrapped, skip_render_check=True)
    assert set(env.observation_space.keys()) == {"speed", "command", "pose"}  # type: ignore[attr-defined]
    env.close()


def test_image_in_space_with_camera_and_action_bounds() -> None:
    env = YawilDriveEnv(town="square", camera=True)
    assert isinstance(env.observation_space, gymnasium.spaces.Dict)
    space = env.observation_space["image"]
    assert space.shape == (88, 200, 3) and space.dtype == np.uint8
    assert isinstance(env.action_space, gymnasium.spaces.Box)
    assert np.allclose(env.action_space.low, [-1, 0, 0]) and np.allclose(env.action_space.high, [1, 1, 1])
    env.close()


def test_reward_is_progress_and_reset_is_seeded() -> None:
    env = YawilDriveEnv(town="square", camera=False, min_route_length=60.0)
    o1, _ = env.reset(seed=4)
    total = 0.0
    for _ in range(60):
        _, r, term, trunc, info = env.step(np.array([0.0, 0.6, 0.0], dtype=np.float32))
        total += r
    assert total > 5.0 and info["route_index"] > 5
    o2, _ = env.reset(seed=4)
    assert np.array_equal(o1["pose"], o2["pose"])
    with pytest.raises(ValueError, match="steer"):
        env.step(np.array([0.0, 0.5], dtype=np.float32))
    with pytest.raises(ValueError, match="Control"):
        env.step(np.array([0.0, 2.0, 0.0], dtype=np.float32))
    env.close()
