"""Conversions between CARLA's frame and types and yawil's, and the camera image pipeline.

CARLA's map frame is left-handed (x forward/east, y to the south of yawil's north, z up) with yaw in degrees
clockwise seen from above; yawil's is right-handed with yaw in radians counter-clockwise. The conversion is
y -> -y and yaw -> -radians(yaw), the same both ways. Controls are the same as CARLA's (steer > 0 = right).
Functions taking CARLA objects only read their attributes, so they import nothing from `carla`; the ones
building CARLA objects import it when called.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from yawil.sim.types import Control, Pose, wrap_angle

CAMERA_WIDTH, CAMERA_HEIGHT, CAMERA_FOV = 800, 600, 100.0
CAMERA_XYZ = (2.0, 0.0, 1.4)  # metres in the vehicle frame (x forward, z up): the protocol's camera
CROP_TOP, CROP_BOTTOM = 115, 510  # rows [top, bottom) of the full image that are kept
OUT_WIDTH, OUT_HEIGHT = 200, 88


def yaw_from_carla(yaw_deg: float) -> float:
    """CARLA yaw (degrees, clockwise) to yawil yaw (radians, counter-clockwise, wrapped)."""
    return wrap_angle(-math.radians(float(yaw_deg)))


def yaw_to_carla(yaw: float) -> float:
    """yawil yaw (radians, CCW) to CARLA yaw (degrees, clockwise), in (-180, 180]."""
    return -math.degrees(wrap_angle(float(yaw))) + 0.0


def xy_from_carla(x: float, y: float) -> tuple[float, float]:
    return float(x), -float(y) + 0.0


def xy_to_carla(x: float, y: float) -> tuple[float, float]:
    return float(x), -float(y) + 0.0


def pose_from_transform(transform: Any) -> Pose:
    """A carla.Transform (or anything with .location.x/.y and .rotation.yaw) as a yawil Pose."""
    x, y = xy_from_carla(transform.location.x, transform.location.y)
    return Pose(x, y, yaw_from_carla(transform.rotation.yaw))


def pose_to_transform(pose: Pose, z: float = 0.0) -> Any:
    """A yawil Pose as a carla.Transform at height z (pitch and roll zero)."""
    import carla

    x, y = xy_to_carla(pose.x, pose.y)
    return carla.Transform(carla.Location(x=x, y=y, z=float(z)), carla.Rotation(pitch=0.0, yaw=yaw_to_carla(pose.yaw), roll=0.0))


def speed_of(velocity: Any) -> float:
    """Speed in m/s of a carla.Vector3D velocity (its norm; the frame flip does not change it)."""
    return float(math.sqrt(velocity.x ** 2 + velocity.y ** 2 + velocity.z ** 2))


def vehicle_control(control: Control) -> Any:
    """A validated yawil Control as a carla.VehicleControl (same conventions, no gear or hand brake)."""
    import carla

    control.validate()
    return carla.VehicleControl(throttle=float(control.throttle), steer=float(control.steer), brake=float(control.brake),
                                hand_brake=False, reverse=False)


def camera_transform() -> Any:
    """The protocol camera's mount on the ego, as a carla.Transform."""
    import carla

    x, y, z = CAMERA_XYZ
    return carla.Transform(carla.Location(x=x, y=y, z=z), carla.Rotation(pitch=0.0, yaw=0.0, roll=0.0))


def bgra_to_rgb(raw: bytes | bytearray | memoryview | np.ndarray, width: int = CAMERA_WIDTH,
                height: int = CAMERA_HEIGHT) -> np.ndarray:
    """carla.Image.raw_data (BGRA, row-major) as an (H, W, 3) uint8 RGB array."""
    buf = np.frombuffer(raw, dtype=np.uint8) if not isinstance(raw, np.ndarray) else raw.reshape(-1).astype(np.uint8, copy=False)
    if buf.size != width * height * 4:
        raise ValueError(f"camera image has {buf.size} bytes, expected {width}x{height}x4 = {width * height * 4} (BGRA)")
    return np.ascontiguousarray(buf.reshape(height, width, 4)[:, :, 2::-1])


def crop_resize(rgb: np.ndarray) -> np.ndarray:
    """The CIL pipeline: rows 115..509 of the 800x600 image, resized to 200x88 (PIL bilinear)."""
    from PIL import Image

    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < CROP_BOTTOM:
        raise ValueError(f"expected an (H>={CROP_BOTTOM}, W, 3) uint8 RGB image, got {rgb.shape} {rgb.dtype}")
    window = np.ascontiguousarray(rgb[CROP_TOP:CROP_BOTTOM])
    out = Image.fromarray(window, mode="RGB").resize((OUT_WIDTH, OUT_HEIGHT), Image.Resampling.BILINEAR)
    return np.asarray(out, dtype=np.uint8)


def observation_image(image: Any) -> np.ndarray:
    """A carla.Image from the protocol camera as Observation.image (88x200x3 uint8 RGB)."""
    return crop_resize(bgra_to_rgb(image.raw_data, int(image.width), int(image.height)))
