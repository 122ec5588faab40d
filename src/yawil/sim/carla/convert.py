"""Conversions between CARLA's frame and types and yawil's, and the camera image pipeline.

CARLA's map frame is left-handed (x forward/east, y to the south of yawil's north, z up) with yaw in degrees
clockwise seen from above; yawil's is right-handed with yaw in radians counter-clockwise. The conversion is
y -> -y and yaw -> -radians(yaw), the same both ways. Controls are the same as CARLA's (steer > 0 = right).
Functions taking CARLA objects only read their attributes, so they import nothing from `carla`; the ones
building CARLA objects import it when called. The semantic camera's tags map to yawil's classes
(`yawil.sim.semantic`) through `CARLA_LABEL_CLASSES`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from yawil.sim import semantic as sem
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


# CARLA's semantic tags (the names of carla.CityObjectLabel) as yawil classes. Both generations are named: the
# tags of 0.9.11-0.9.13 ("Vehicles", "Roads" = 7, ...) and the CityScapes-ordered ones of 0.9.14+ ("Car", "Roads"
# = 1, ...); the values come from the client package at run time (`carla_tag_values`), which equals the server's
# version. CARLA has no crosswalk tag and no light state in its tags (a light is
# traffic_light whatever it shows). A tag not listed here reads as unlabeled.
CARLA_LABEL_CLASSES: dict[str, str] = {
    "NONE": "unlabeled", "None": "unlabeled", "Unlabeled": "unlabeled",
    "Roads": "road", "RoadLines": "lane_marking", "Sidewalks": "sidewalk",
    "Terrain": "terrain", "Ground": "terrain", "Water": "terrain", "RailTrack": "terrain",
    "Buildings": "building", "Walls": "building", "Bridge": "building",
    "Poles": "pole", "TrafficSigns": "pole", "TrafficLight": "traffic_light",
    "Vegetation": "vegetation", "Sky": "sky",
    "Fences": "static", "GuardRail": "static", "Static": "static", "Dynamic": "static", "Other": "static", "Rock": "static",
    "Vehicles": "vehicle", "Car": "vehicle", "Truck": "vehicle", "Bus": "vehicle", "Train": "vehicle",
    "Motorcycle": "vehicle", "Bicycle": "vehicle",
    "Pedestrians": "pedestrian", "Rider": "pedestrian",
}


def carla_tag_values() -> dict[str, int]:
    """The installed client's semantic tags, name -> value (carla.CityObjectLabel; "Any" is a filter, left out)."""
    import carla

    return {str(k): int(v) for k, v in carla.CityObjectLabel.names.items() if str(k) != "Any"}


def semantic_lut(tags: Mapping[str, int]) -> np.ndarray:
    """(256,) uint8: the yawil class id of each CARLA tag value, given the tags' names and values."""
    lut = np.full(256, sem.UNLABELED, dtype=np.uint8)
    for name, value in tags.items():
        if not 0 <= int(value) < 256:
            raise ValueError(f"CARLA tag {name!r} = {value}: a semantic tag is one byte")
        lut[int(value)] = sem.CLASS_ID[CARLA_LABEL_CLASSES.get(name, "unlabeled")]
    return lut


def observation_semantic(image: Any, lut: np.ndarray) -> np.ndarray:
    """A carla.Image of the semantic camera (tag in the red channel) as Observation.semantic: (88, 200) uint8
    yawil class ids. The crop is the RGB camera's, and the resize takes each output pixel's centre (ids do not
    blend), which is where the embedded renderer samples its pixels too."""
    width, height = int(image.width), int(image.height)
    buf = np.frombuffer(image.raw_data, dtype=np.uint8)
    if buf.size != width * height * 4 or height < CROP_BOTTOM:
        raise ValueError(f"semantic image has {buf.size} bytes for {width}x{height}; expected BGRA with at least "
                         f"{CROP_BOTTOM} rows")
    rows = CROP_TOP + ((np.arange(OUT_HEIGHT) + 0.5) * (CROP_BOTTOM - CROP_TOP) / OUT_HEIGHT).astype(np.int64)
    cols = ((np.arange(OUT_WIDTH) + 0.5) * width / OUT_WIDTH).astype(np.int64)
    red = buf.reshape(height, width, 4)[:, :, 2]
    out: np.ndarray = lut[red[np.ix_(rows, cols)]]
    return out
