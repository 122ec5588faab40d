"""What a collection is made of: how episodes are drawn and which frames are kept (CollectConfig), and how a
learner shares the wheel with the expert in an on-policy round (OnPolicy). Both are stored in the dataset's
manifest, so a resumed collection is checked against them. Rules and options: docs/expert.md.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from yawil.sim.weather import get_weather

COLLISION_POLICIES: tuple[str, ...] = ("trim", "keep", "discard")
DEFAULT_FRAMES = 200_000  # `collect`'s frame budget when neither frames nor episodes is given (the paper's size)


@dataclass(frozen=True)
class CollectConfig:
    """How episodes are made and which frames are kept. Stored in the dataset's manifest (resume checks it)."""

    town: str = "town01"
    weathers: tuple[str, ...] = ("ClearNoon", "WetNoon", "HardRainNoon", "ClearSunset")
    vehicles: tuple[int, int] = (10, 30)  # drawn uniformly per episode, inclusive
    pedestrians: tuple[int, int] = (5, 20)
    min_route_length: float = 200.0  # metres
    camera: bool = True
    # steering noise (the paper: 10% of the data)
    noise_fraction: float = 0.10  # expected fraction of frames with a perturbation
    noise_amplitude: float = 0.5  # a burst adds a constant offset drawn from U[-a, a] to the steer
    noise_duration: tuple[float, float] = (0.5, 1.0)  # seconds, uniform per burst
    # frame thinning
    blocked_speed: float = 0.1  # m/s: below this the ego is "blocked"
    blocked_after: float = 2.0  # s blocked before frames are thinned
    blocked_keep_every: int = 10  # then keep every Nth frame
    straight_keep: float = 0.5  # fraction of frames kept on long straights
    straight_window: float = 20.0  # m: "long straight" = LANEFOLLOW, no curvature within this distance around
    straight_curvature: float = 0.01  # 1/m: below this the route counts as straight
    lane_follow_turn_curvature: float = 0.02  # 1/m (radius < 50 m): a lane-follow curve
    lane_follow_turn_ahead: float = 10.0  # m ahead of the ego examined for lane_follow_turn
    # episode end
    on_collision: str = "trim"  # trim: keep frames up to trim_seconds before it; keep: all; discard: drop episode
    trim_seconds: float = 2.0
    stuck_seconds: float = 90.0  # end the episode (outcome "stuck") after this long without moving 1 m
    max_episode_frames: int = 0  # > 0: end an episode after this many steps (outcome "frame_limit"), for demos

    def __post_init__(self) -> None:
        if not self.weathers:
            raise ValueError("CollectConfig.weathers must name at least one weather")
        for w in self.weathers:
            get_weather(w)
        for name in ("vehicles", "pedestrians"):
            lo, hi = getattr(self, name)
            if not (isinstance(lo, int) and isinstance(hi, int)) or lo < 0 or hi < lo:
                raise ValueError(f"CollectConfig.{name} must be (lo, hi) integers with 0 <= lo <= hi, got {(lo, hi)!r}")
        if not 0.0 <= self.noise_fraction < 1.0:
            raise ValueError(f"CollectConfig.noise_fraction must be in [0, 1), got {self.noise_fraction!r}")
        if not 0.0 <= self.noise_amplitude <= 1.0:
            raise ValueError(f"CollectConfig.noise_amplitude must be in [0, 1], got {self.noise_amplitude!r}")
        lo, hi = self.noise_duration
        if not 0.0 < lo <= hi:
            raise ValueError(f"CollectConfig.noise_duration must be (lo, hi) seconds with 0 < lo <= hi, got {(lo, hi)!r}")
        if not 0.0 < self.straight_keep <= 1.0:
            raise ValueError(f"CollectConfig.straight_keep must be in (0, 1], got {self.straight_keep!r}")
        if self.max_episode_frames < 0:
            raise ValueError(f"CollectConfig.max_episode_frames must be >= 0 (0: no limit), got {self.max_episode_frames!r}")
        if self.blocked_keep_every < 1:
            raise ValueError(f"CollectConfig.blocked_keep_every must be >= 1, got {self.blocked_keep_every!r}")
        if self.on_collision not in COLLISION_POLICIES:
            raise ValueError(f"CollectConfig.on_collision must be one of {COLLISION_POLICIES}, got {self.on_collision!r}")
        for name in ("min_route_length", "blocked_speed", "blocked_after", "straight_window", "straight_curvature",
                     "lane_follow_turn_curvature", "lane_follow_turn_ahead", "trim_seconds", "stuck_seconds"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"CollectConfig.{name} must be a finite number >= 0, got {v!r}")
        if self.min_route_length >= 1e5:  # the scenario's own bound (validate_scenario), checked before the folder
            raise ValueError(f"CollectConfig.min_route_length must be below 1e5 m, got {self.min_route_length!r}")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


@dataclass(frozen=True)
class OnPolicy:
    """How a learner shares the wheel with the expert in a DAgger round (docs/training.md, "DAgger").

    The expert labels every frame whoever drives. It drives a segment itself with probability `beta` (one
    draw per `segment_seconds`, or per episode when 0), and takes the wheel from the learner for
    `takeover_seconds` when the learner strays `takeover_lateral` m from the route, would need more than
    `takeover_decel` m/s^2 to stop for the stop point the expert brakes for, or stands `takeover_stall` s
    while the expert would drive: these recovery frames are what behaviour cloning never shows.
    """

    round: int = 1
    beta: float = 0.0
    segment_seconds: float = 0.0
    takeover_lateral: float = 2.0
    takeover_decel: float = 4.0
    takeover_stall: float = 4.0
    takeover_seconds: float = 3.0

    def __post_init__(self) -> None:
        if isinstance(self.round, bool) or not isinstance(self.round, int) or not 1 <= self.round <= 32767:
            raise ValueError(f"OnPolicy.round must be an int in [1, 32767], got {self.round!r}")
        if not 0.0 <= self.beta <= 1.0:
            raise ValueError(f"OnPolicy.beta must be in [0, 1], got {self.beta!r}")
        for name in ("segment_seconds", "takeover_lateral", "takeover_decel", "takeover_stall", "takeover_seconds"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"OnPolicy.{name} must be a finite number >= 0, got {v!r}")
