"""Synthetic episodes for tests and benchmarks: no simulator, but images that compress like rendered ones.

The images are smooth (sky gradient, road in perspective, lane marks, buildings, cars) with mild pixel noise,
because compression figures measured on white noise or flat colour would both be meaningless. Labels follow
the paper's shapes: mostly lane-follow, a few junction turns, exclusive throttle/brake, steer near zero.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from yawil.data.manifest import Manifest, read_manifest
from yawil.data.schema import IMAGE_SHAPE, FrameRecord
from yawil.data.writer import DatasetWriter
from yawil.sim.types import RoadOption
from yawil.sim.weather import TRAIN_WEATHERS

H, W, _ = IMAGE_SHAPE


def synthetic_image(rng: np.random.Generator, offset: float = 0.0, noise_sigma: float = 1.0) -> np.ndarray:
    """A (88, 200, 3) uint8 street-like image; `offset` in [-1, 1] shifts the road sideways (a curve)."""
    img = np.empty((H, W, 3), dtype=np.float32)
    horizon = int(rng.integers(30, 40))
    yy = np.arange(H, dtype=np.float32)[:, None]
    xx = np.arange(W, dtype=np.float32)[None, :]
    top = rng.uniform(0.3, 0.6, 3) * 255
    bottom = rng.uniform(0.6, 0.95, 3) * 255
    t = np.clip(yy / max(horizon, 1), 0, 1)[..., None]
    img[:horizon] = (top * (1 - t) + bottom * t)[:horizon]
    grass = rng.uniform(0.2, 0.5, 3) * 255
    img[horizon:] = grass
    # Buildings: boxes standing on the horizon, shaded top to bottom.
    for _ in range(int(rng.integers(3, 8))):
        x0 = int(rng.integers(0, W - 10))
        w = int(rng.integers(10, 50))
        h = int(rng.integers(8, horizon))
        color = rng.uniform(0.2, 0.8, 3) * 255
        shade = np.linspace(1.0, 0.8, h, dtype=np.float32)[:, None, None]
        img[horizon - h : horizon, x0 : x0 + w] = color * shade
    # Road: a trapezoid widening towards the camera, gray with a gradient, centre line dashed.
    depth = np.clip((yy - horizon) / (H - horizon), 0, 1)  # 0 at horizon, 1 at the bottom
    centre = W / 2 + offset * 60 * (1 - depth) ** 2
    half = 4 + depth * 110
    on_road = (np.abs(xx - centre) < half) & (yy >= horizon)
    road_gray = (90 + 40 * depth)[..., None]  # (H, 1, 1)
    img = np.where(on_road[..., None], road_gray, img)
    dash = (np.abs(xx - centre) < 0.5 + 1.5 * depth) & (np.sin(depth * 40 + rng.uniform(0, 6)) > 0) & (yy > horizon)
    img[dash] = (230, 220, 120)
    # Other cars: dark boxes on the road.
    for _ in range(int(rng.integers(0, 3))):
        d = rng.uniform(0.1, 0.6)
        row = int(horizon + d * (H - horizon))
        size = int(4 + 30 * d)
        col = int(W / 2 + rng.uniform(-0.5, 0.5) * (4 + d * 110))
        img[max(row - size, 0) : row, max(col - size, 0) : col + size] = rng.uniform(0.05, 0.9, 3) * 255
    if noise_sigma > 0:
        img += rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def synthetic_episode(rng: np.random.Generator, frames: int, k: int, image_noise: float = 1.0) -> list[FrameRecord]:
    """Labels of a plausible drive: lane-follow segments, lane-follow curves and junction turns."""
    records: list[FrameRecord] = []
    x, y, yaw = rng.uniform(-100, 100, 2).tolist() + [float(rng.uniform(-np.pi, np.pi))]
    i, frame = 0, 0
    while i < frames:
        seg = int(rng.integers(5, 30))
        kind = rng.choice(["follow", "follow", "curve", "left", "right", "straight"])
        command = {
            "follow": RoadOption.LANEFOLLOW,
            "curve": RoadOption.LANEFOLLOW,
            "left": RoadOption.LEFT,
            "right": RoadOption.RIGHT,
            "straight": RoadOption.STRAIGHT,
        }[str(kind)]
        turn = {"left": -0.4, "right": 0.4, "curve": float(rng.choice([-0.3, 0.3]))}.get(str(kind), 0.0)
        for _ in range(min(seg, frames - i)):
            steer = float(np.clip(turn + rng.normal(0, 0.05), -1, 1))
            braking = rng.random() < 0.15
            throttle = 0.0 if braking else float(rng.uniform(0.2, 0.8))
            brake = float(rng.uniform(0.3, 1.0)) if braking else 0.0
            speed = float(rng.uniform(0, 7))
            yaw = float(np.arctan2(np.sin(yaw - 0.02 * steer), np.cos(yaw - 0.02 * steer)))
            x, y = x + 0.5 * np.cos(yaw), y + 0.5 * np.sin(yaw)
            gy = np.cumsum(np.full(k, -turn * 0.2, dtype=np.float32)) + rng.normal(0, 0.01, k).astype(np.float32)
            records.append(
                FrameRecord(
                    image=synthetic_image(rng, offset=turn, noise_sigma=image_noise),
                    steer=steer,
                    throttle=throttle,
                    brake=brake,
                    speed=speed,
                    command=int(command),
                    guidance_yaw=gy.astype(np.float32),
                    guidance_xy=rng.uniform(-1, 1, 2 * k).astype(np.float32),
                    guidance_sim_yaw=(gy + rng.normal(0, 0.01, k)).astype(np.float32),
                    pose=(float(x), float(y), yaw),
                    frame=frame,
                    noise=bool(rng.random() < 0.1),
                    lane_follow_turn=kind == "curve",
                    # privileged labels derived from the draws above (no new draw: older fixtures stay the same)
                    target_speed=0.0 if braking else speed, speed_reason=4 if braking else 0,
                    lead_distance=10.0 if braking else 50.0, lead_speed=0.0, light_ahead=0,
                )
            )
            i += 1
            frame += int(rng.integers(1, 3))  # collectors may skip frames
    return records


def write_synthetic_dataset(
    root: str | os.PathLike[str],
    episodes: int = 3,
    frames: int = 20,
    k: int = 4,
    seed: int = 0,
    first_episode: int = 0,
    weathers: tuple[str, ...] = TRAIN_WEATHERS,
    town: str = "town01",
    image_noise: float = 1.0,
    writer_kwargs: dict[str, Any] | None = None,
) -> Manifest:
    """A small complete dataset (manifest + episode files), deterministic in `seed`."""
    config = {"guidance": {"spacing": 2.0, "count": k, "reference": "route"}, "collector": {"synthetic": True}}
    with DatasetWriter(root, config, **(writer_kwargs or {})) as w:
        for e in range(first_episode, first_episode + episodes):
            rng = np.random.default_rng([seed, e])
            with w.begin_episode(e, town, weathers[e % len(weathers)], seed * 100_000 + e, {"route_length": 100.0}) as ep:
                for rec in synthetic_episode(rng, frames, k, image_noise):
                    ep.append(rec)
                ep.commit("goal")
    return read_manifest(root)
