"""The Gymnasium environments: registered by `import yawil`, Dict observation with route and guidance, the
expert's action in info on request, a bird's-eye rgb_array render, and clear errors for bad options."""

from __future__ import annotations

import subprocess
import sys
from typing import Any

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import yawil
from yawil.expert import Expert
from yawil.guidance import GuidanceConfig, compute_guidance, yaw_guidance
from yawil.gym_env import YawilDriveEnv

IDS = ("yawil/Town01-v0", "yawil/Town02-v0", "yawil/Square-v0")


def test_import_yawil_registers_without_heavy_imports() -> None:
    """The documented example, in a fresh interpreter: only `import yawil`, no simulator or torch at import."""
    code = (
        "import sys, gymnasium as gym, yawil\n"
        f"assert all(i in gym.registry for i in {IDS!r})\n"
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'matplotlib', 'panda3d')\n"
        "               or m.startswith('yawil.sim'))\n"
        "assert not heavy, heavy\n"
        "env = gym.make('yawil/Square-v0', camera=False)\n"
        "obs, info = env.reset(seed=0)\n"
        "assert {'route', 'guidance'} <= set(obs), obs.keys()\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]


def test_registered_and_passes_check_env() -> None:
    for env_id in IDS:
        assert env_id in gymnasium.registry
    assert [i for i, _ in yawil.GYM_ENVS] == list(IDS)
    env = gymnasium.make("yawil/Square-v0", camera=False, vehicles=3, pedestrians=3, render_mode="rgb_array",
                         expert_action=True)
    check_env(env.unwrapped)  # the render check included: it makes a second env through the spec
    assert set(env.observation_space.keys()) == {"speed", "command", "pose", "route", "route_ego", "guidance"}  # type: ignore[attr-defined]
    env.close()


def test_image_is_the_main_key_with_camera_and_action_bounds() -> None:
    env = YawilDriveEnv(town="square", camera=True)
    assert isinstance(env.observation_space, gymnasium.spaces.Dict)
    space = env.observation_space["image"]
    assert space.shape == (88, 200, 3) and space.dtype == np.uint8
    assert isinstance(env.action_space, gymnasium.spaces.Box)
    assert np.allclose(env.action_space.low, [-1, 0, 0]) and np.allclose(env.action_space.high, [1, 1, 1])
    obs, _ = env.reset(seed=1)
    assert obs["image"].shape == (88, 200, 3) and obs["image"].dtype == np.uint8
    assert env.observation_space.contains(obs)
    env.close()


def test_reward_is_progress_and_reset_is_seeded() -> None:
    env = YawilDriveEnv(town="square", camera=False, min_route_length=60.0)
    o1, _ = env.reset(seed=4)
    total, rewards = 0.0, []
    for _ in range(60):
        _, r, term, trunc, info = env.step(np.array([0.0, 0.6, 0.0], dtype=np.float32))
        total += r
        rewards.append(r)
    assert total > 5.0 and info["route_index"] > 5
    cruise = rewards[-10:]  # continuous progress: every step at speed moves it, not whole metres now and then
    assert all(0.05 < r < 2.0 for r in cruise) and len({round(r, 6) for r in cruise}) > 2
    assert info["success"] is False and info["reason"] is None
    o2, _ = env.reset(seed=4)
    assert np.array_equal(o1["pose"], o2["pose"]) and np.array_equal(o1["route"], o2["route"])
    with pytest.raises(ValueError, match="steer"):
        env.step(np.array([0.0, 0.5], dtype=np.float32))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([0.0, np.nan, 0.0], dtype=np.float32))
    env.step(np.array([0.0, 2.0, -1.0], dtype=np.float32))  # clipped to the Box, as documented (it used to raise)
    env.close()


def test_an_episode_ends_with_success_and_the_benchmark_s_reason() -> None:
    """The expert reaches the goal (success, "goal"); driving into the first obstacle ends the episode at the
    collision with its kind as the reason (an option keeps driving)."""
    env = YawilDriveEnv(town="square", camera=False, min_route_length=60.0, expert_action=True)
    _, info = env.reset(seed=1)
    for _ in range(2000):
        _, _, term, trunc, info = env.step(info["expert_action"])
        if term or trunc:
            break
    assert term and info["success"] is True and info["reason"] == "goal"
    env.close()
    env = YawilDriveEnv(town="town01", camera=False, vehicles=0, min_route_length=100.0)
    env.reset(seed=3)
    for _ in range(3000):  # full throttle, steering left: off the road into something static
        _, _, term, trunc, info = env.step(np.array([-0.6, 1.0, 0.0], dtype=np.float32))
        if term or trunc:
            break
    assert term and info["success"] is False and info["reason"].startswith("collision_"), info["reason"]
    env.close()


def test_route_and_guidance_come_from_the_project_guidance() -> None:
    env = YawilDriveEnv(town="square", camera=False)
    obs, _ = env.reset(seed=2)
    raw = env.last_observation
    assert raw is not None
    g, _ = compute_guidance(raw.route.xy, raw.route.lane_yaw, (raw.pose.x, raw.pose.y), raw.pose.yaw, raw.bounds)
    assert obs["guidance"].shape == (15,) and obs["route"].shape == (16, 2)
    assert np.allclose(obs["guidance"], g.yaw, atol=1e-6)
    assert np.allclose(yaw_guidance(obs["route"].astype(np.float64)), obs["guidance"], atol=1e-4)  # same points
    assert np.allclose(obs["route"][0], raw.route.xy[0], atol=0.5)  # starts at the ego's projection
    # the same points in the car's frame: the ego's projection near the origin, the route ahead at x > 0 (the
    # start pose follows its lane), and the map points recovered by the inverse rotation
    ego = obs["route_ego"].astype(np.float64)
    assert np.linalg.norm(ego[0]) < 2.0 and ego[-1, 0] > 20.0 and abs(ego[-1, 1]) < ego[-1, 0]
    c, s_ = np.cos(raw.pose.yaw), np.sin(raw.pose.yaw)
    back = np.column_stack((c * ego[:, 0] - s_ * ego[:, 1], s_ * ego[:, 0] + c * ego[:, 1])) + [raw.pose.x, raw.pose.y]
    assert np.allclose(back, obs["route"], atol=1e-3) and env.observation_space.contains(obs)
    obs["guidance"][0] = 9.0  # the arrays are the caller's own
    env.close()

    env = YawilDriveEnv(town="square", camera=False, guidance="xy", guidance_config=GuidanceConfig(count=5, spacing=3.0))
    obs, _ = env.reset(seed=2)
    assert obs["guidance"].shape == (10,) and obs["route"].shape == (6, 2)
    assert np.all(np.abs(obs["guidance"]) <= 1.0) and env.observation_space.contains(obs)
    assert np.allclose(np.linalg.norm(np.diff(obs["route"], axis=0), axis=1), 3.0, atol=0.05)
    env.close()

    env = YawilDriveEnv(town="square", camera=False, guidance=None)  # the observation before route/guidance
    assert set(env.observation_space.keys()) == {"speed", "command", "pose"}  # type: ignore[attr-defined]
    obs, _ = env.reset(seed=2)
    assert set(obs) == {"speed", "command", "pose"}
    env.close()


def _drive(env: YawilDriveEnv, seed: int, steps: int) -> list[tuple[dict[str, Any], float, dict[str, Any]]]:
    obs, info = env.reset(seed=seed)
    out = [(obs, 0.0, info)]
    for _ in range(steps):
        obs, r, term, trunc, info = env.step(info["expert_action"])
        out.append((obs, r, info))
        if term or trunc:
            break
    return out


def test_expert_action_in_info_drives_and_is_deterministic() -> None:
    env = YawilDriveEnv(town="square", camera=False, vehicles=2, pedestrians=2, expert_action=True)
    a = _drive(env, seed=7, steps=40)
    b = _drive(env, seed=7, steps=40)
    assert len(a) == len(b) == 41
    for (oa, ra, ia), (ob, rb, ib) in zip(a, b, strict=True):
        assert ra == rb and np.array_equal(ia["expert_action"], ib["expert_action"])
        assert all(np.array_equal(oa[k], ob[k]) for k in oa)
    assert sum(r for _, r, _ in a) > 10.0  # the expert's actions drive the route
    first = a[0][2]["expert_action"]
    assert first.dtype == np.float32 and first.shape == (3,) and env.action_space.contains(first)
    env.reset(seed=7)
    control = Expert().act(env.last_observation)  # type: ignore[arg-type]
    assert np.allclose(first, [control.steer, control.throttle, control.brake])

    _, info = env.reset(seed=7, options={"expert_action": False})
    assert "expert_action" not in info
    env.close()
    plain = YawilDriveEnv(town="square", camera=False)
    _, info = plain.reset(seed=7)
    assert "expert_action" not in info
    _, info = plain.reset(seed=7, options={"expert_action": True})
    assert np.array_equal(info["expert_action"], first)
    plain.close()


def test_rgb_array_render_is_a_birdseye_view() -> None:
    env = YawilDriveEnv(town="square", camera=False, render_mode="rgb_array")
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.render()
    env.reset(seed=3)
    img0 = env.render()
    assert isinstance(img0, np.ndarray) and img0.dtype == np.uint8 and img0.ndim == 3 and img0.shape[2] == 3
    assert max(img0.shape[:2]) == 480
    ego = np.all(img0 == (255, 45, 149), axis=2)
    assert ego.sum() >= 9  # the ego is painted
    for _ in range(30):
        env.step(np.array([0.0, 0.7, 0.0], dtype=np.float32))
    img1 = env.render()
    assert img1 is not None and img1.shape == img0.shape
    moved = np.all(img1 == (255, 45, 149), axis=2)
    assert moved.sum() >= 9 and not np.array_equal(ego, moved)
    env.reset(seed=3)
    again = env.render()
    assert again is not None and np.array_equal(again, img0)  # the same episode draws the same frame
    env.close()
    off = YawilDriveEnv(town="square", camera=False)
    off.reset(seed=3)
    assert off.render() is None
    off.close()


def test_bad_options_give_one_clear_value_error() -> None:
    for make in (lambda **kw: gymnasium.make("yawil/Square-v0", camera=False, **kw),
                 lambda **kw: YawilDriveEnv(town="square", camera=False, **kw)):
        with pytest.raises(ValueError, match="render_mode='human' is not supported.*headless.*'rgb_array'") as err:
            make(render_mode="human")
        assert "\n" not in str(err.value)
        with pytest.raises(ValueError, match="render_mode 'ansi'.*'rgb_array'"):
            make(render_mode="ansi")
        with pytest.raises(ValueError, match="guidance must be one of"):
            make(guidance="yaws")
        with pytest.raises(ValueError, match="expert_action must be True or False"):
            make(expert_action="yes")
        with pytest.raises(ValueError, match="vehicles must be a non-negative integer"):
            make(vehicles=-1)
        with pytest.raises(ValueError, match="unknown weather"):
            make(weather="Foggy")
        with pytest.raises(ValueError, match="GuidanceConfig has no field"):
            make(guidance_config={"cnt": 3})
    with pytest.raises(ValueError, match="unknown option 'camra'.*did you mean 'camera'"):
        gymnasium.make("yawil/Square-v0", camra=False)
    with pytest.raises(ValueError, match="unknown town"):
        gymnasium.make("yawil/Square-v0", town="nowhere")
    env = YawilDriveEnv(town="square", camera=False)
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.step(np.zeros(3, dtype=np.float32))
    with pytest.raises(ValueError, match=r"unknown reset option\(s\) \['expert'\]; known: expert_action"):
        env.reset(options={"expert": True})
    with pytest.raises(ValueError, match="reset option expert_action must be True or False"):
        env.reset(options={"expert_action": 1})
    env.close()


def test_rgb_array_list_through_make() -> None:
    env = gymnasium.make("yawil/Square-v0", camera=False, render_mode="rgb_array_list")
    env.reset(seed=0)
    env.step(np.array([0.0, 0.5, 0.0], dtype=np.float32))
    frames = env.render()
    assert isinstance(frames, list) and len(frames) == 2 and np.asarray(frames[0]).ndim == 3
    env.close()
