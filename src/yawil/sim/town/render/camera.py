"""The camera model of the benchmark protocol, kept apart from Panda3D so that it can be read and tested alone.

The camera is the benchmark's 800x600, FOV 100 camera at (2.0, 0, 1.4) m in the vehicle frame, of which
rows 115..509 are kept and resized to 200x88. The renderer draws only that window, with an off-centre lens
that has the same projection (docs/rendering.md derives it); `reference_projection` is the 800x600 + crop +
resize pipeline in numpy, against which the tests check the lens.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from yawil.sim.types import Pose


@dataclass(frozen=True)
class CameraConfig:
    """The camera of the benchmark protocol, and how much of the town is drawn."""

    width: int = 200
    height: int = 88
    full_width: int = 800
    full_height: int = 600
    fov_deg: float = 100.0  # horizontal, of the full image
    mount: tuple[float, float, float] = (2.0, 0.0, 1.4)  # vehicle frame: x forward, y left, z up
    crop_top: int = 115  # rows [crop_top, crop_bottom) of the full image are kept
    crop_bottom: int = 510
    near: float = 0.3
    far: float = 120.0
    tile_size: float = 40.0  # static geometry is grouped in tiles this big for frustum culling
    lod_distance: float = 70.0  # buildings of tiles farther than this are drawn without window bands
    haze_ceiling: float = 6.0  # assumed height of what is seen above the horizon (haze approximation)
    haze_max_depth: float = 60.0  # cap of that depth estimate, so the horizon rows do not fog near walls

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.full_width <= 0 or self.full_height <= 0:
            raise ValueError(f"CameraConfig sizes must be positive, got {self}")
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"CameraConfig.fov_deg={self.fov_deg} must be in (0, 180)")
        if not 0 <= self.crop_top < self.crop_bottom <= self.full_height:
            raise ValueError(
                f"CameraConfig crop rows [{self.crop_top}, {self.crop_bottom}) must lie in [0, {self.full_height}]"
            )
        if not 0.0 < self.near < self.far:
            raise ValueError(f"CameraConfig needs 0 < near < far, got near={self.near} far={self.far}")
        if self.tile_size < 0.0 or self.haze_ceiling <= self.mount[2]:
            raise ValueError("CameraConfig.tile_size must be >= 0 and haze_ceiling above the camera height")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels of the full image."""
        return self.full_width / 2.0 / math.tan(math.radians(self.fov_deg) / 2.0)

    @property
    def film_offset_px(self) -> float:
        """Vertical offset (up positive) of the crop window's centre from the principal point."""
        return self.full_height / 2.0 - (self.crop_top + self.crop_bottom) / 2.0


def camera_pose(ego: Pose, config: CameraConfig = CameraConfig()) -> tuple[float, float, float, float]:
    """World position (x, y, z) and yaw of the camera mounted on `ego`."""
    mx, my, mz = config.mount
    c, s = math.cos(ego.yaw), math.sin(ego.yaw)
    return ego.x + c * mx - s * my, ego.y + s * mx + c * my, mz, ego.yaw


def sky_card_extent(config: CameraConfig = CameraConfig()) -> tuple[float, float, float, float]:
    """(distance, half width, top, bottom) in camera metres of the camera-fixed sky card: just inside the far
    plane, 5 % larger than the view; its part below the horizon (z < 0) shows the far ground. The RGB sky and
    the semantic camera's far ground share it, so that both cover the same pixels."""
    cfg = config
    dist = cfg.far * 0.9
    half_w = dist * (cfg.full_width / 2 / cfg.focal_px) * 1.05
    top = dist * (cfg.film_offset_px + (cfg.crop_bottom - cfg.crop_top) / 2) / cfg.focal_px * 1.05
    bottom = dist * (cfg.film_offset_px - (cfg.crop_bottom - cfg.crop_top) / 2) / cfg.focal_px * 1.05
    return dist, half_w, top, bottom


def reference_projection(ego: Pose, points: np.ndarray, config: CameraConfig = CameraConfig()) -> np.ndarray:
    """Where world points land in the 200x88 image by the protocol's own pipeline.

    Pinhole projection into the full 800x600 image, crop of rows [crop_top, crop_bottom), resize of the
    window to width x height (pixel-centre convention of PIL/OpenCV: continuous coordinates scale). Returns
    (N, 2) continuous (column, row); NaN for points behind the camera.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cx, cy, cz, yaw = camera_pose(ego, config)
    dx, dy, dz = pts[:, 0] - cx, pts[:, 1] - cy, pts[:, 2] - cz
    fwd = dx * math.cos(yaw) + dy * math.sin(yaw)
    left = -dx * math.sin(yaw) + dy * math.cos(yaw)
    f = config.focal_px
    with np.errstate(divide="ignore", invalid="ignore"):
        u = config.full_width / 2.0 - f * left / fwd
        v = config.full_height / 2.0 - f * dz / fwd
    col = u * config.width / config.full_width
    row = (v - config.crop_top) * config.height / (config.crop_bottom - config.crop_top)
    out = np.stack([col, row], axis=1)
    out[fwd <= 0.0] = np.nan
    return out
