"""Weather effects added to the rendered image in numpy: haze by approximate depth, and rain streaks.

Panda3D's software renderer has no fog and its depth buffer cannot be read back, so both effects are
applied after the render, the same way for both backends, so that their images agree.
"""

from __future__ import annotations

import numpy as np

from yawil.sim.town.render.camera import CameraConfig
from yawil.sim.weather import Weather


def haze_map(w: Weather, cfg: CameraConfig) -> np.ndarray:
    """Per-row haze weight (height, 1, 1) from an approximate depth (docs/rendering.md).

    Below the horizon a pixel is taken to see the ground: depth = f * cam_height / (v - v_horizon).
    Above it, a "ceiling" at `haze_ceiling` metres: depth = f * (ceiling - cam_height) / (v_horizon - v).
    Depth is capped at `haze_max_depth` (near the horizon the estimate grows without bound, while what
    is seen there is often a wall 20 m away). Weight = haze_max * (1 - exp(-depth / visibility)),
    visibility = 60 m / haze.
    """
    if w.haze <= 0.0:
        return np.zeros((cfg.height, 1, 1), np.float32)
    rows = (np.arange(cfg.height) + 0.5) * (cfg.crop_bottom - cfg.crop_top) / cfg.height + cfg.crop_top
    dv = rows - cfg.full_height / 2.0
    h = cfg.mount[2]
    with np.errstate(divide="ignore"):
        depth = np.where(dv > 0, cfg.focal_px * h / np.abs(dv), cfg.focal_px * (cfg.haze_ceiling - h) / np.abs(dv))
    depth = np.minimum(depth, cfg.haze_max_depth)
    vis = 60.0 / w.haze
    alpha = min(1.0, 0.6 + 0.4 * w.haze) * (1.0 - np.exp(-depth / vis))
    return alpha.astype(np.float32).reshape(-1, 1, 1)


_RAIN_COLOR = np.array([205.0, 208.0, 215.0], np.float32)
_RAIN_LAYERS = 8
_RAIN_ALPHA = np.float32(0.35)


def rain_layers(rain: float, h: int, w: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """A few layers of slanted streaks as (rows, cols) pixel lists; frame k shows layer k % 8, shifted
    sideways by a multiple of 53 px. Precomputed per weather so that a frame blends only the streak
    pixels; each image is a function of `frame` alone."""
    n = int(round(rain * 0.05 * h * w))
    if n == 0:
        return []
    layers = []
    for k in range(_RAIN_LAYERS):
        rng = np.random.default_rng([0x5241494E, k])
        x0, y0, length = rng.uniform(0, w, n), rng.uniform(-6, h, n), rng.integers(3, 8, n)
        t = np.arange(7)
        ys = (y0[:, None] + t).astype(np.int64)
        xs = (x0[:, None] + 0.3 * t).astype(np.int64) % w
        ok = (t < length[:, None]) & (ys >= 0) & (ys < h)
        flat = np.unique(ys[ok] * w + xs[ok])  # a pixel hit by two streaks is blended once
        layers.append((flat // w, flat % w))
    return layers


def post_effects(img: np.ndarray, haze: np.ndarray, haze_color: np.ndarray,
                 rain: list[tuple[np.ndarray, np.ndarray]], frame: int) -> np.ndarray:
    """Haze toward the horizon colour by approximate depth, then rain streaks (layers of `rain_layers`)."""
    out = img.astype(np.float32)
    out += (haze_color - out) * haze
    if rain:
        k = len(rain)
        rows, cols = rain[frame % k]
        cols = (cols + (frame // k) * 53) % img.shape[1]
        out[rows, cols] += (_RAIN_COLOR - out[rows, cols]) * _RAIN_ALPHA
    return (out + 0.5).astype(np.uint8)
