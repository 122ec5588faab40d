"""The record of one frame and the on-disk layout of an episode file (schema version 2; version 1 still reads).

Everything that reads or writes a yawil dataset agrees through this module: field names, dtypes, per-frame
shapes and valid ranges. The validation here is shared by the writer (refuse bad data before it reaches
disk) and by `yawil data check` (find bad data that reached disk anyway). No torch, no h5py here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from yawil.sim.types import RoadOption

SCHEMA_VERSION = 2
READABLE_VERSIONS: tuple[int, ...] = (1, 2)
EPISODE_FORMAT = "yawil-episode"
DATASET_FORMAT = "yawil-dataset"
IMAGE_SHAPE: tuple[int, int, int] = (88, 200, 3)  # H, W, C; RGB uint8

# Road options a frame may carry. VOID is not one: the collector maps it to LANEFOLLOW, as CARLA's agents do.
VALID_COMMANDS: tuple[int, ...] = (
    int(RoadOption.LEFT),
    int(RoadOption.RIGHT),
    int(RoadOption.STRAIGHT),
    int(RoadOption.LANEFOLLOW),
)
COMMAND_NAMES: dict[int, str] = {c: RoadOption(c).name for c in VALID_COMMANDS}

# name -> (numpy dtype, per-frame shape as a function of K). One HDF5 dataset per field, first axis = frame.
SCALAR_FIELDS: dict[str, str] = {
    "steer": "float32",
    "throttle": "float32",
    "brake": "float32",
    "speed": "float32",
    "command": "int8",
    "frame": "int64",
    "noise": "uint8",  # 0/1, stored as uint8 so any HDF5 tool reads it (h5py's bool is an enum)
    "lane_follow_turn": "uint8",
    # schema 2: who drove, and what the expert knew (docs/dataset.md)
    "driver": "uint8",  # DRIVERS index: the expert's own episode, the learner (DAgger), the expert taking over
    "round": "int16",  # DAgger round (0: expert data)
    "target_speed": "float32",  # m/s the expert aimed for; NaN: unknown (schema 1)
    "speed_reason": "int8",  # SPEED_REASONS index of what set it; -1: unknown
    "lead_distance": "float32",  # m from the front bumper to the vehicle followed, LEAD_RANGE when none; NaN unknown
    "lead_speed": "float32",  # its speed along the route (m/s), 0 when none; NaN unknown
    "light_ahead": "int8",  # 1: a red or yellow stop line within LIGHT_RANGE m; 0: none; -1: unknown
}
# Fields a schema-1 file lacks, and the value a reader fills in for them ("unknown" where the truth is).
V2_FIELDS: dict[str, float] = {
    "driver": 0, "round": 0, "target_speed": math.nan, "speed_reason": -1,
    "lead_distance": math.nan, "lead_speed": math.nan, "light_ahead": -1,
}
DRIVERS: tuple[str, ...] = ("expert", "learner", "takeover")
SPEED_REASONS: tuple[str, ...] = (
    "cruise", "curve", "red_light", "yellow_light", "vehicle", "pedestrian", "junction", "goal",
)
LEAD_RANGE = 50.0  # m: a vehicle followed farther than this counts as none
LIGHT_RANGE = 30.0  # m
# Float fields where NaN is allowed and means "unknown" (older files, or a frame made without an expert).
MAYBE_UNKNOWN: frozenset[str] = frozenset({"target_speed", "lead_distance", "lead_speed"})
VECTOR_FIELDS: dict[str, tuple[str, int]] = {  # name -> (dtype, multiple of K)
    "guidance_yaw": ("float32", 1),
    "guidance_xy": ("float32", 2),
    "guidance_sim_yaw": ("float32", 1),
}
POSE_FIELD = ("pose", "float64", 3)
LABEL_FIELDS: tuple[str, ...] = (*SCALAR_FIELDS, *VECTOR_FIELDS, POSE_FIELD[0])
ALL_FIELDS: tuple[str, ...] = ("image", *LABEL_FIELDS)

# Episode file attributes (root group). JSON-valued ones are stored as str.
REQUIRED_ATTRS: tuple[str, ...] = (
    "format",
    "schema_version",
    "episode",
    "town",
    "weather",
    "seed",
    "outcome",
    "frames",
    "K",
    "route_length",
    "config",
    "meta",
)


def field_shape(name: str, k: int) -> tuple[int, ...]:
    """Per-frame shape of a field for guidance length K."""
    if name == "image":
        return IMAGE_SHAPE
    if name in SCALAR_FIELDS:
        return ()
    if name in VECTOR_FIELDS:
        return (VECTOR_FIELDS[name][1] * k,)
    if name == POSE_FIELD[0]:
        return (POSE_FIELD[2],)
    raise KeyError(f"unknown field {name!r}")


def field_dtype(name: str) -> np.dtype[Any]:
    if name == "image":
        return np.dtype("uint8")
    if name in SCALAR_FIELDS:
        return np.dtype(SCALAR_FIELDS[name])
    if name in VECTOR_FIELDS:
        return np.dtype(VECTOR_FIELDS[name][0])
    if name == POSE_FIELD[0]:
        return np.dtype(POSE_FIELD[1])
    raise KeyError(f"unknown field {name!r}")


@dataclass
class FrameRecord:
    """One frame as the expert saw and drove it. The controls are the expert's own, never the noisy ones."""

    image: np.ndarray  # (88, 200, 3) uint8 RGB
    steer: float
    throttle: float
    brake: float
    speed: float  # m/s
    command: int  # RoadOption value: LEFT=1 RIGHT=2 STRAIGHT=3 LANEFOLLOW=4
    guidance_yaw: np.ndarray  # (K,) float32
    guidance_xy: np.ndarray  # (2K,) float32
    guidance_sim_yaw: np.ndarray  # (K,) float32
    pose: tuple[float, float, float]  # x, y, yaw
    frame: int  # index within the episode; strictly increasing, gaps allowed
    noise: bool = False  # a steering perturbation was applied to the car at this frame
    lane_follow_turn: bool = False  # on a lane-follow curve (square subsets)
    driver: int = 0  # DRIVERS index
    round: int = 0
    target_speed: float = math.nan
    speed_reason: int = -1
    lead_distance: float = math.nan
    lead_speed: float = math.nan
    light_ahead: int = -1

    @classmethod
    def from_labels(cls, image: np.ndarray, labels: dict[str, np.ndarray], r: int) -> FrameRecord:
        """Row `r` of an episode's label columns (as `EpisodeReader.labels()` gives them) with its image."""
        def scalar(name: str) -> Any:
            v = labels[name][r]
            return float(v) if field_dtype(name).kind == "f" else int(v)

        return cls(
            image=image,
            **{name: scalar(name) for name in SCALAR_FIELDS if name not in ("noise", "lane_follow_turn")},
            noise=bool(labels["noise"][r]),
            lane_follow_turn=bool(labels["lane_follow_turn"][r]),
            guidance_yaw=np.asarray(labels["guidance_yaw"][r]),
            guidance_xy=np.asarray(labels["guidance_xy"][r]),
            guidance_sim_yaw=np.asarray(labels["guidance_sim_yaw"][r]),
            pose=tuple(float(v) for v in labels["pose"][r]),  # type: ignore[arg-type]
        )

    @property
    def k(self) -> int:
        return int(np.asarray(self.guidance_yaw).shape[0]) if np.ndim(self.guidance_yaw) == 1 else -1

    def validate(self, where: str = "record") -> FrameRecord:
        """Raise ValueError naming the field and value when the record breaks the schema."""
        img = self.image
        if not isinstance(img, np.ndarray) or img.shape != IMAGE_SHAPE or img.dtype != np.uint8:
            got = f"{getattr(img, 'shape', None)} {getattr(img, 'dtype', type(img).__name__)}"
            raise ValueError(f"{where}: image must be a {IMAGE_SHAPE} uint8 array, got {got}")
        for name, lo, hi in (("steer", -1.0, 1.0), ("throttle", 0.0, 1.0), ("brake", 0.0, 1.0)):
            check_scalar(where, name, getattr(self, name), lo, hi)
        check_scalar(where, "speed", self.speed, 0.0, math.inf)
        if isinstance(self.command, bool) or int(self.command) != self.command:
            raise ValueError(f"{where}: command must be an int, got {self.command!r}")
        if int(self.command) not in VALID_COMMANDS:
            raise ValueError(
                f"{where}: command={self.command!r} is not a valid road option; expected one of "
                f"{', '.join(f'{v} ({n})' for v, n in COMMAND_NAMES.items())} (map VOID to LANEFOLLOW)"
            )
        k = self.k
        if k < 1:
            raise ValueError(f"{where}: guidance_yaw must be a 1-D array of K >= 1 values, got shape {np.shape(self.guidance_yaw)}")
        for name in VECTOR_FIELDS:
            arr = np.asarray(getattr(self, name))
            want = field_shape(name, k)
            if arr.shape != want:
                raise ValueError(f"{where}: {name} must have shape {want} (K={k}), got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{where}: {name} contains NaN or inf")
        pose = np.asarray(self.pose, dtype=np.float64)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"{where}: pose must be 3 finite numbers (x, y, yaw), got {self.pose!r}")
        if isinstance(self.frame, bool) or int(self.frame) != self.frame or int(self.frame) < 0:
            raise ValueError(f"{where}: frame must be an int >= 0, got {self.frame!r}")
        for name, lo, hi in (("driver", 0, len(DRIVERS) - 1), ("round", 0, 32767),
                             ("speed_reason", -1, len(SPEED_REASONS) - 1), ("light_ahead", -1, 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= int(v) <= hi:
                raise ValueError(f"{where}: {name} must be an int in [{lo}, {hi}], got {v!r}")
        for name in sorted(MAYBE_UNKNOWN):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating)) and not isinstance(v, bool)) or (
                    not math.isnan(float(v)) and not 0.0 <= float(v) < math.inf):
                raise ValueError(f"{where}: {name} must be a number >= 0 or NaN (unknown), got {v!r}")
        return self


def check_scalar(where: str, name: str, value: object, lo: float, hi: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{where}: {name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{where}: {name} is {v} (must be finite)")
    if not lo <= v <= hi:
        raise ValueError(f"{where}: {name}={v} is out of range [{lo}, {hi}]")


def label_problems(labels: dict[str, np.ndarray], k: int) -> list[str]:
    """Everything wrong with an episode's label columns (not the images); empty when all is well.

    Used by `check` and by the Dataset when it indexes an episode, so both judge files the same way.
    """
    problems: list[str] = []
    n = None
    for name in LABEL_FIELDS:
        if name not in labels:
            problems.append(f"missing dataset {name!r}")
            continue
        arr = labels[name]
        want_shape = field_shape(name, k)
        if arr.shape[1:] != want_shape:
            problems.append(f"{name}: per-frame shape {arr.shape[1:]} != expected {want_shape} (K={k})")
        if arr.dtype != field_dtype(name):
            problems.append(f"{name}: dtype {arr.dtype} != expected {field_dtype(name)}")
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            problems.append(f"{name}: {arr.shape[0]} rows, other fields have {n}")
        if arr.dtype.kind == "f":
            bad = np.isinf(arr) if name in MAYBE_UNKNOWN else ~np.isfinite(arr)
            if bad.any():
                rows = np.nonzero(bad.reshape(arr.shape[0], -1).any(axis=1))[0]
                problems.append(f"{name}: NaN or inf at {len(rows)} row(s), first row {int(rows[0])}")
    if problems:
        return problems
    for name, lo, hi in (("steer", -1.0, 1.0), ("throttle", 0.0, 1.0), ("brake", 0.0, 1.0), ("speed", 0.0, math.inf)):
        arr = labels[name]
        out = (arr < lo) | (arr > hi)
        if out.any():
            i = int(np.nonzero(out)[0][0])
            problems.append(f"{name}: {int(out.sum())} value(s) out of [{lo}, {hi}], first {float(arr[i])} at row {i}")
    cmd = labels["command"]
    bad_cmd = ~np.isin(cmd, VALID_COMMANDS)
    if bad_cmd.any():
        i = int(np.nonzero(bad_cmd)[0][0])
        problems.append(f"command: {int(bad_cmd.sum())} invalid value(s), first {int(cmd[i])} at row {i}")
    for name in ("noise", "lane_follow_turn"):
        if (labels[name] > 1).any():
            problems.append(f"{name}: values other than 0/1")
    for name, lo, hi in (("driver", 0, len(DRIVERS) - 1), ("round", 0, 32767),
                         ("speed_reason", -1, len(SPEED_REASONS) - 1), ("light_ahead", -1, 1)):
        arr = labels[name]
        out = (arr < lo) | (arr > hi)
        if out.any():
            problems.append(f"{name}: {int(out.sum())} value(s) out of [{lo}, {hi}], first {int(arr[np.nonzero(out)[0][0]])}")
    for name in sorted(MAYBE_UNKNOWN):
        if (labels[name] < 0).any():
            problems.append(f"{name}: negative values (expected >= 0, or NaN for unknown)")
    frames = labels["frame"]
    if frames.size and (frames[0] < 0 or (np.diff(frames) <= 0).any()):
        problems.append("frame: indices must be >= 0 and strictly increasing")
    return problems
